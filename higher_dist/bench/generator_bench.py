"""`higher-bench generator`: how well the instruction generator learns from N expert pairs.

The measurement itself (how pairs are drawn, what seen and unseen mean) is
`higher_dist.learning.hindsight.generator_measure`. Prints a table, then one JSON line with `pairs`,
`seen_exact_match`, `unseen_exact_match`, times.
"""
from __future__ import annotations

import argparse
import json

import torch

from higher_dist.config import ConfigError
from higher_dist.config_flags import explicit_overrides
from higher_dist.config_presets import make_config
from higher_dist.learning.hindsight.generator_measure import measure_generator


def format_table(result: dict) -> str:
    cols = ("exact", "color", "type", "shade", "size", "parse_rate")
    lines = [f"generator: {result['pairs']} training pairs, {result['steps']} steps "
             f"({result['train_s']} s, {result['steps_per_s']} steps/s), "
             f"{result['eval_pairs']} evaluation pairs per set",
             f"{'goals':<8}" + "".join(f"{c:>11}" for c in cols)]
    for name in ("seen", "unseen"):
        lines.append(f"{name:<8}" + "".join(f"{result[name][c]:>11.3f}" for c in cols))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="higher-bench generator", description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=5000, help="expert training pairs (default: 5000)")
    parser.add_argument("--steps", type=int, default=1500,
                        help="Adam steps of batch 64 (default: 1500; about a minute on one CPU thread)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-pairs", type=int, default=2000, help="fresh pairs per evaluation set")
    parser.add_argument("--world", default="paper", help="paper | small")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--set", action="append", default=[], metavar="generator.FIELD=VALUE",
                        help="measure a variant of the generator, e.g. --set generator.beam_width=8 (repeatable)")
    args = parser.parse_args(argv)
    if args.pairs < 1 or args.steps < 1 or args.eval_pairs < 1:
        parser.error("--pairs, --steps and --eval-pairs must be >= 1")
    torch.set_num_threads(args.threads)
    # The generator HIGhER runs on that world (its world's lr and sizes), as `higher-reproduce generator`
    # does, with any --set on top: only the generator's own fields shape this measurement.
    try:
        overrides = explicit_overrides(argparse.Namespace(set=args.set))
        others = [key for key in overrides if not key.startswith("generator.")]
        if others:
            raise ConfigError(f"--set {others[0]}: only generator.* fields shape this measurement")
        cfg = make_config("higher", args.world, **overrides)
    except ConfigError as e:
        parser.error(str(e))
    result = measure_generator(args.pairs, args.steps, args.seed, cfg.world, args.eval_pairs, cfg=cfg.generator)
    print(format_table(result))
    print(json.dumps({k: v for k, v in result.items() if k not in ("seen", "unseen")}
                     | {f"{s}_{c}": round(result[s][c], 4) for s in ("seen", "unseen")
                        for c in ("color", "type", "shade", "size", "parse_rate")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
