"""`higher-bench SUBCOMMAND [options]`: benchmarks that print figures (speed is never asserted in tests).

Each subcommand is a callable(argv) registered in COMMANDS; its module is imported only when run, so
one benchmark's heavy imports do not slow the others.
"""
from __future__ import annotations

import sys
from typing import Callable


def _world(argv: list[str]) -> int:
    from higher_dist.bench.world_bench import main
    return main(argv)


def _learner(argv: list[str]) -> int:
    from higher_dist.bench.learner_bench import main
    return main(argv)


def _wire(argv: list[str]) -> int:
    from higher_dist.bench.wire_bench import main
    return main(argv)


def _generator(argv: list[str]) -> int:
    from higher_dist.bench.generator_bench import main
    return main(argv)


def _cluster(argv: list[str]) -> int:
    from higher_dist.bench.cluster_bench import main
    return main(argv)


def _all(argv: list[str]) -> int:
    from higher_dist.bench.run_all import main
    return main(argv)


COMMANDS: dict[str, Callable[[list[str]], int]] = {
    "world": _world, "learner": _learner, "wire": _wire, "generator": _generator, "cluster": _cluster,
    "all": _all,
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
    return int(COMMANDS[argv[0]](argv[1:]) or 0)
