"""`higher-bench SUBCOMMAND [options]`: benchmarks that print figures (speed is never asserted in tests).

Each subcommand is a module registered in COMMANDS, with a main(argv); it is imported only when run, so
one benchmark's heavy imports do not slow the others.
"""
from __future__ import annotations

import importlib
import sys


# name -> module under higher_dist.bench with a main(argv) -> int
COMMANDS: dict[str, str] = {
    "world": "world_bench", "learner": "learner_bench", "wire": "wire_bench",
    "generator": "generator_bench", "cluster": "cluster_bench", "soak": "soak_bench", "all": "run_all",
    "time-to-success": "time_to_success_bench", "gpu": "gpu_bench", "checkpoint": "checkpoint_bench",
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        known = ", ".join(sorted(COMMANDS))
        print(f"usage: higher-bench {{{known}}} [options]   (higher-bench NAME --help for its options)")
        if argv and argv[0] not in ("-h", "--help"):
            print(f"higher-bench: unknown benchmark {argv[0]!r}; choose one of {known}", file=sys.stderr)
            return 2
        return 0 if argv else 2
    module = importlib.import_module(f"higher_dist.bench.{COMMANDS[argv[0]]}")
    return int(module.main(argv[1:]) or 0)
