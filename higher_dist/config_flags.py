"""The config flags every command that starts a run shares (--preset, --world, --profile, --set FIELD=VALUE,
...) and the Config they make. `--set` takes any field by its dotted path (docs/configuration.md) and a
JSON value (a bare word is a string)."""
from __future__ import annotations

import argparse
import json
from typing import Any

from higher_dist.config import PRESETS, PROFILES, WORLDS, Config, ConfigError, from_dict
from higher_dist.config_presets import make_config


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def add_config_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=PRESETS, default="higher", help="the paper's method to run")
    p.add_argument("--world", choices=WORLDS, default="paper", help="paper: 10x10, 10 objects; small: tests")
    p.add_argument("--profile", choices=PROFILES, default="default",
                   help="default: our tuned settings; paper: the paper's (docs/paper_settings.md)")
    p.add_argument("--actors", type=positive_int, default=None,
                   help="actor processes (higher-cluster's default fits the machine: half its cores, 1 to 8)")
    p.add_argument("--envs-per-actor", type=positive_int, default=None, help="environments per actor")
    p.add_argument("--frames", type=positive_int, default=None, help="stop after this many env frames")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="learner device: cpu or cuda[:N]")
    p.add_argument("--threads", type=positive_int, default=1, help="torch threads per process")
    p.add_argument("--tensorboard", action="store_true", help="also write TensorBoard event files")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override any config field, e.g. --set dqn.lr=0.001 (repeatable)")


def config_from_args(args: argparse.Namespace) -> Config:
    overrides: dict[str, Any] = {"seed": args.seed, "device": args.device, "torch_threads": args.threads,
                                 "tensorboard": args.tensorboard}
    for name in ("actors", "envs_per_actor", "frames"):
        if getattr(args, name, None) is not None:
            overrides[name] = getattr(args, name)
    for item in args.set:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected FIELD=VALUE")
        key, value = item.split("=", 1)
        overrides[key.strip()] = _parse_value(value)
    cfg = make_config(args.preset, args.world, args.profile, **overrides)
    # Round trip through the wire form so --set values get the declared types (e.g. tuples).
    return from_dict(cfg.to_dict())
