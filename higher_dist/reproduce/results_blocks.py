"""`python -m higher_dist.reproduce.results_blocks` (part of `make docs`): docs/results.md's tables from
the archived plans' reports.

docs/results.md is prose around tables that `higher-reproduce --report` writes into each archive's own
results.md (the folders of `ARCHIVES` below). Each copied part sits between `<!-- gen:NAME -->` and
`<!-- /gen -->`; NAME picks the part, and its prefix (a key of `ARCHIVES`) picks the archive. Redraw an
archive's report, run this, and the prose keeps its tables current. `--check` only compares (exit code 1
on a difference).
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parents[2] / "docs"
RESULTS = DOCS / "results.md"
ARCHIVES = {  # block prefix -> archive: every experiment on the earlier defaults and on the paper's profile,
    # then `main` on today's defaults on the paper world and on BabyAI-PickupDist-v0 and -PickupLoc-v0
    "": DOCS / "runs" / "claims-default", "paper-": DOCS / "runs" / "claims-paper",
    "main-": DOCS / "runs" / "main-defaults", "pickupdist-": DOCS / "runs" / "pickupdist-defaults",
    "pickuploc-": DOCS / "runs" / "pickuploc-defaults"}
BLOCK = re.compile(r"(<!-- gen:([\w-]+) -->\n)(.*?)(<!-- /gen -->)", re.S)

# A part of a report: the first line that starts with its marker, then the lines a table goes on with.
TABLES = {"claims": "| claim of the paper", "methods": "| method |", "composition": "| share of the replay",
          "generator": "| expert pairs |", "trigger": "| trigger | seed"}


def _table(lines: list[str], marker: str) -> list[str]:
    start = next((i for i, line in enumerate(lines) if line.startswith(marker)), None)
    if start is None:
        return []
    out = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        out.append(line)
    return out


def part(report: str, name: str) -> list[str]:
    """The lines of one part of a plan's report; a name the report does not have is an error."""
    lines = report.splitlines()
    if name == "machine":
        found = [line for line in lines if line.startswith(("Written ", "Time: "))]
    elif name == "commands":
        found = [line for line in lines if line.startswith("    higher-reproduce ")]
    elif name == "budget":  # the plan's budget, without the sentence on the paper's that follows it
        found = [line.split(" the paper's numbers")[0] for line in lines if line.startswith("World ")]
    elif name in TABLES:
        found = _table(lines, TABLES[name])
    else:
        raise ValueError(f"results.md: unknown block gen:{name} (known: machine, commands, budget, "
                         f"{', '.join(TABLES)})")
    if not found:
        raise ValueError(f"results.md: block gen:{name}: its report has no such part")
    return found


def fill(text: str, reports: dict[str, str]) -> str:
    """`text` with every gen block replaced by its part of the report its prefix names."""
    def replace(match: re.Match) -> str:
        name = match.group(2)
        prefix = next(p for p in sorted(reports, key=len, reverse=True) if name.startswith(p))
        body = part(reports[prefix], name[len(prefix):])
        return match.group(1) + "\n".join(body) + "\n" + match.group(4)
    return BLOCK.sub(replace, text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="compare only; exit 1 on a difference")
    args = parser.parse_args(argv)
    reports = {prefix: (path / "results.md").read_text() for prefix, path in ARCHIVES.items()}
    current = RESULTS.read_text()
    wanted = fill(current, reports)
    if args.check:
        if wanted != current:
            print(f"{RESULTS} differs from its archives' reports: run `make docs`", file=sys.stderr)
            return 1
        return 0
    RESULTS.write_text(wanted)
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
