"""A launcher killed outright (SIGKILL: no handler, no cleanup) takes its roles with it: each gets SIGTERM
from the kernel, checkpoints as on any SIGTERM and exits, so nothing is left holding the run's ports."""
from __future__ import annotations

import signal
import time

import psutil
import pytest

from hd_harness import learner_pid, start_cluster

pytestmark = pytest.mark.slow


def test_roles_end_with_a_killed_launcher(tmp_path):
    run_dir = tmp_path / "run"
    watch, launcher, _ = start_cluster(run_dir, tmp_path, frames=1_000_000, actors=1)
    try:
        watch.wait_for("frames flowing", lambda r: r.get("frames", 0) > 0 and r.get("updates", 0) > 0, timeout=180)
        launcher.snapshot()
        roles = [p for p in psutil.Process(launcher.pid).children(recursive=True)]
        assert len(roles) >= 3 and learner_pid(launcher) in {p.pid for p in roles}
        launcher.send(signal.SIGKILL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE
                                                  for p in roles):
            time.sleep(0.5)
        left = [p.pid for p in roles if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
        assert left == [], f"roles outlived their launcher: {left}\n" + watch.diagnostics()
        # They ended as on SIGTERM: the learner wrote its checkpoint on the way out.
        assert (run_dir / "learner.ckpt").exists()
    finally:
        watch.cleanup()
