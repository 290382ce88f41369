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


COMMANDS: dict[str, Callable[[list[str]], int]] = {
    "world": _world,
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
