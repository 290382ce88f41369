"""A resumed run is the run it continues: its config comes from the run directory's config.json, not from
the command line.

Flags given with `--resume` are compared with the run's config, field by field. One that leaves the run
as it is passes silently; one in `CHANGEABLE_ON_RESUME` (how long the run goes on, and how it is laid out
on the machines, none of which changes what is learned per frame) is applied and recorded in the run's
`history.jsonl`; any other change is refused with a message that names the field, its value in the run
and the value asked for, so a forgotten `--preset` or a stray `--set dqn.lr=...` cannot silently turn
the run into another experiment.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from higher_dist.config import Config, ConfigError, from_dict, override

# Fields a resume may change: the budget, and the layout on the machines and the reporting around the run.
CHANGEABLE_ON_RESUME = ("frames", "actors", "torch_threads", "device", "actor_device", "stats_every_s",
                        "checkpoint_every_s", "tensorboard")
# Flags that name a whole family of settings: they must match the run's, or be left out.
_NAMED = {"preset": lambda c: c.preset, "world": lambda c: c.world.name, "profile": lambda c: c.profile}
HISTORY_FILE = "history.jsonl"


def _get(cfg: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg


def saved_config(run_dir: str | Path) -> Config:
    """The run's own config (config.json), refused by name when missing or unreadable."""
    path = Path(run_dir) / "config.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"--resume: {path} does not exist; is {run_dir} a run directory?") from None
    except (OSError, json.JSONDecodeError) as e:
        raise ConfigError(f"--resume: cannot read {path} ({e})") from None
    try:
        return from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"--resume: {path} is not a config this version can run: {e}") from None


def resume_config(saved: Config, explicit: dict[str, Any]) -> tuple[Config, dict[str, list]]:
    """The config a resume runs with, and the changes it makes ({field: [old, new]}).

    `explicit`: what the command line set, by dotted field name (plus preset, world, profile), with
    values as `--set` gives them. Anything not in it keeps the run's value."""
    cfg = saved
    changes: dict[str, list] = {}
    for key, value in explicit.items():
        if key in _NAMED:
            current = _NAMED[key](saved)
            if value != current:
                raise ConfigError(f"--resume: --{key} {value} differs from the run's {key} {current!r} "
                                  "(config.json); leave it out, a resumed run keeps its config")
            continue
        try:
            asked = from_dict(override(cfg, **{key: value}).to_dict())
        except TypeError as e:
            raise ConfigError(f"{key}: {e}") from None
        old, new = _get(cfg, key), _get(asked, key)
        if old == new:
            continue
        if key not in CHANGEABLE_ON_RESUME:
            raise ConfigError(
                f"--resume: {key} is {_show(old)} in the run's config.json, {_show(new)} asked for; a resumed run "
                f"keeps its config (only {', '.join(CHANGEABLE_ON_RESUME)} may change; start a new --run-dir "
                "for another experiment)")
        changes[key] = [_plain(old), _plain(new)]
        cfg = asked
    return cfg, changes


def record_resume(run_dir: str | Path, changes: dict[str, list], argv: list[str] | None = None) -> None:
    """One line per resume in the run's history.jsonl: when, the command, what it changed."""
    line = {"time": round(time.time(), 3), "event": "resume", "argv": list(sys.argv if argv is None else argv),
            "changes": changes}
    with open(Path(run_dir) / HISTORY_FILE, "a") as f:
        f.write(json.dumps(line) + "\n")


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _show(value: Any) -> str:
    return json.dumps(_plain(value))
