"""One run of the `generator` experiment: the instruction generator trained on N expert pairs, measured
on fresh pairs with seen (training) and unseen (held-out) goals. It is the generator benchmark's path
(`higher_dist.learning.hindsight.generator_measure.measure_generator`), with the generator's config taken from the run's profile
(the flags after `--`, as higher-cluster would read them). Writes OUT/result.json atomically at the end;
an interrupted measurement has no checkpoint and starts again (about a minute)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from higher_dist.config import ConfigError
from higher_dist.config_flags import add_config_flags, config_from_args
from higher_dist.learning.hindsight.generator_measure import measure_generator
from higher_dist.rundir import atomic_write_bytes


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    own, config_argv = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    p = argparse.ArgumentParser("higher-reproduce generator run")
    p.add_argument("--pairs", type=int, required=True)
    p.add_argument("--steps", type=int, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--world", default="paper")
    p.add_argument("--eval-pairs", type=int, default=1000)
    p.add_argument("--out", required=True)
    args = p.parse_args(own)
    config_parser = argparse.ArgumentParser("higher-reproduce generator run (config flags)")
    add_config_flags(config_parser)
    try:
        cfg = config_from_args(config_parser.parse_args(
            ["--preset", "higher", "--world", args.world, "--seed", str(args.seed), *config_argv]))
    except ConfigError as e:
        print(f"higher-reproduce generator run: error: {e}", file=sys.stderr)
        return 2
    torch.set_num_threads(cfg.torch_threads or 1)
    result = measure_generator(args.pairs, args.steps, args.seed, cfg.world, args.eval_pairs, cfg=cfg.generator)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "result.json", json.dumps(result, indent=2).encode())
    print(json.dumps({k: result[k] for k in ("pairs", "seed", "seen_exact_match", "unseen_exact_match", "train_s")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
