"""The config flags every command that starts a run shares (--preset, --world, --profile, --set FIELD=VALUE,
...) and the Config they make. `--set` takes any field by its dotted path (docs/configuration.md) and a
JSON value (a bare word is a string)."""
from __future__ import annotations

import argparse
import json
from typing import Any

from higher_dist.config import PRESETS, PROFILES, WORLDS, Config, ConfigError, from_dict, is_babyai_world
from higher_dist.config_presets import make_config


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


class DefaultsHelp(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the help already names it or there is none to
    show (a switch that is off, or a default the command works out at run time and the help describes)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        quiet = action.default in (None, False, argparse.SUPPRESS) or action.option_strings == []
        if quiet or "default" in text or "%(default)" in text:
            return text
        return f"{text} (default: %(default)s)"


def parse_count(text: str) -> int:
    """An integer count as every command reads one: 2000000, 2_000_000 or 2e6 (a whole number)."""
    try:
        value = float(text.replace("_", "")) if any(c in text.lower() for c in "e.") else int(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value != int(value):
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}")
    return int(value)


def positive_int(text: str) -> int:
    value = parse_count(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def non_negative_int(text: str) -> int:
    value = parse_count(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def world_name(text: str) -> str:
    """--world: one of our worlds or a BabyAI level id (whether minigrid has that level is checked when
    the world is built)."""
    if text in WORLDS or is_babyai_world(text):
        return text
    raise argparse.ArgumentTypeError(f"unknown world {text!r}; choose one of {', '.join(WORLDS)} "
                                     f"or a BabyAI pickup, go-to or open level id such as BabyAI-PickupDist-v0")


def add_config_flags(p: argparse.ArgumentParser, layout_actors: bool = False) -> None:
    """`layout_actors`: the command picks the actor count for its host when --actors is not given
    (higher-cluster); elsewhere the config's own count stands."""
    # Defaults are None here and filled in by config_from_args, so that `explicit_overrides` can tell a
    # flag the user gave from a default (a resumed run compares only what was given with its config).
    p.add_argument("--preset", choices=PRESETS, default=None, help="the paper's method to run (default: higher)")
    p.add_argument("--world", type=world_name, default=None, metavar="WORLD",
                   help="paper: 10x10, 10 objects; small: tests; or a BabyAI pickup, go-to or open level id such as "
                        "BabyAI-PickupDist-v0 or BabyAI-GoToLocal-v0 (default: paper)")
    p.add_argument("--profile", choices=PROFILES, default=None,
                   help="default: our tuned settings; paper: the paper's (docs/paper_settings.md) (default: default)")
    p.add_argument("--actors", type=positive_int, default=None,
                   help="actor processes (default: " + ("the layout for this host, launch/layout.py)" if layout_actors
                                                         else f"{Config.actors})"))
    p.add_argument("--envs-per-actor", type=positive_int, default=None,
                   help="environments per actor (default: the preset's, 32 on the paper world)")
    p.add_argument("--frames", type=positive_int, default=None,
                   help="stop after this many env frames (default: the preset's, 5000000 on the paper world)")
    p.add_argument("--seed", type=int, default=None, help="the run's seed (default: 0)")
    p.add_argument("--device", default=None,
                   help="learner device: auto (CUDA when present), cpu or cuda[:N] (default: auto)")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="the learner's torch threads (default: every core the other roles leave, launch/layout.py)")
    p.add_argument("--tensorboard", action="store_true", help="also write TensorBoard event files (default: off)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override any config field, e.g. --set dqn.lr=0.001 (repeatable; docs/configuration.md)")
    p.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")


# flag -> config field, for the flags that set one field each
_FLAG_FIELDS = {"seed": "seed", "device": "device", "threads": "torch_threads", "actors": "actors",
                "envs_per_actor": "envs_per_actor", "frames": "frames"}


def explicit_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """What the command line set, by dotted field name (preset, world and profile by their own names):
    flags left at their defaults are not in it."""
    out: dict[str, Any] = {name: getattr(args, name) for name in ("preset", "world", "profile")
                           if getattr(args, name, None) is not None}
    for flag, name in _FLAG_FIELDS.items():
        if getattr(args, flag, None) is not None:
            out[name] = getattr(args, flag)
    if getattr(args, "tensorboard", False):
        out["tensorboard"] = True
    for item in getattr(args, "set", []):
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected FIELD=VALUE")
        key, value = item.split("=", 1)
        out[key.strip()] = _parse_value(value)
    return out


def config_from_args(args: argparse.Namespace) -> Config:
    overrides = explicit_overrides(args)
    preset = overrides.pop("preset", "higher")
    world = overrides.pop("world", "paper")
    profile = overrides.pop("profile", "default")
    cfg = make_config(preset, world, profile, **overrides)
    # Round trip through the wire form so --set values get the declared types (e.g. tuples).
    return from_dict(cfg.to_dict())


def resumed_config(args: argparse.Namespace, run_dir: str) -> Config:
    """The config of a run continued with --resume: the run's config.json, with the flags given checked
    against it (resume.py); a change that is allowed is recorded in the run's history.jsonl."""
    from higher_dist.resume import record_resume, resume_config, saved_config

    cfg, changes = resume_config(saved_config(run_dir), explicit_overrides(args))
    if not getattr(args, "print_config", False):
        record_resume(run_dir, changes)
    return cfg
