"""Test-only entry point: a real role (its process, sockets and checkpoints) in which one step of its own code
is made to raise once the role has written a given number of checkpoints. Production code has no hook for this: the
fault is patched in from here, before the role's main runs.

    python faulty_role.py TARGET CHECKPOINTS SKIP RECORD ROLE [ROLE'S FLAGS...]

TARGET: what raises, "module:attribute" or "module:Class.method", e.g.
        higher_dist.learning.replay:PrioritizedReplay._write (one episode of a batch insert).
CHECKPOINTS: how many checkpoints the role writes before TARGET may raise.
SKIP:   calls of TARGET after that that still work before the one that raises
        (1 with _write: the failure comes part-way through a batch).
RECORD: a file that gets one JSON line per checkpoint written: its path, sha256 and mtime_ns.
ROLE:   learner or relabeler (higher_dist.cli's entry point).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import os
import sys
from pathlib import Path


def _patch(target: str, wrap) -> None:
    module_name, _, attribute = target.partition(":")
    owner = importlib.import_module(module_name)
    *path, name = attribute.split(".")
    for part in path:
        owner = getattr(owner, part)
    setattr(owner, name, wrap(getattr(owner, name)))


def main() -> int:
    target, checkpoints, skip, record, role, *flags = sys.argv[1:]
    state = {"checkpoints": 0, "calls": 0}

    def saving(real):
        def save_checkpoint(self, role_name, checkpoint_state):
            path = real(self, role_name, checkpoint_state)
            digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
            with open(record, "a") as f:
                f.write(json.dumps({"path": str(path), "sha256": digest, "mtime_ns": os.stat(path).st_mtime_ns}) + "\n")
            state["checkpoints"] += 1
            return path
        return save_checkpoint

    def failing(real):
        def step(*args, **kwargs):
            if state["checkpoints"] >= int(checkpoints):
                state["calls"] += 1
                if state["calls"] > int(skip):
                    raise RuntimeError(f"injected fault in {target.partition(':')[2]}")
            return real(*args, **kwargs)
        return step

    _patch("higher_dist.rundir:RunDir.save_checkpoint", saving)
    _patch(target, failing)
    from higher_dist import cli

    return getattr(cli, f"{role}_main")(flags)


if __name__ == "__main__":
    sys.exit(main())
