"""The progress view of a plan: a live rich table in a terminal, plain lines otherwise (logs, CI, tests).

Each row is a run: its state, frames (or pairs) done of its budget, its frame rate and its latest
greedy evaluation on training and held-out goals. The footer holds the plan's progress and ETA.
"""
from __future__ import annotations

import sys
import time

from higher_dist.reproduce.status import human_seconds

LINE_EVERY_S = 15.0  # plain mode: one progress line this often


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def summary(rows: list[dict], eta: float | None) -> str:
    total = sum(r["total"] for r in rows) or 1
    done = sum(r["done"] for r in rows)
    n_done = sum(1 for r in rows if str(r["state"]).startswith("done"))
    running = sum(1 for r in rows if r["state"] == "running")
    return (f"plan {100 * done / total:.0f}%: {n_done}/{len(rows)} runs done, {running} running; "
            f"ETA {'-' if eta is None else human_seconds(eta)}")


class PlainView:
    def __init__(self, stream=None):
        self.stream = stream or sys.stdout
        self.last = 0.0

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass

    def event(self, text: str) -> None:
        print(f"[higher-reproduce {time.strftime('%H:%M:%S')}] {text}", file=self.stream, flush=True)

    def update(self, rows: list[dict], eta: float | None) -> None:
        if time.time() - self.last < LINE_EVERY_S:
            return
        self.last = time.time()
        running = [f"{r['name']} {r['done']}/{r['total']}" for r in rows if r["state"] == "running"]
        self.event(summary(rows, eta) + (f" ({', '.join(running)})" if running else ""))


class LiveView(PlainView):
    """A rich table redrawn in place; events scroll above it."""

    def __init__(self):
        super().__init__()
        from rich.console import Console
        from rich.live import Live

        self.console = Console()
        self.live = Live(console=self.console, refresh_per_second=2, transient=False)

    def __enter__(self):
        self.live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.live.__exit__(*exc)

    def event(self, text: str) -> None:
        self.console.print(f"[dim]{time.strftime('%H:%M:%S')}[/dim] {text}")

    def update(self, rows: list[dict], eta: float | None) -> None:
        from rich.table import Table

        table = Table(title="higher-reproduce", caption=summary(rows, eta), expand=False)
        for name, justify in (("run", "left"), ("state", "left"), ("progress", "right"), ("frames/s", "right"),
                              ("greedy train", "right"), ("greedy held-out", "right")):
            table.add_column(name, justify=justify)
        colours = {"running": "cyan", "done": "green", "done (earlier)": "green", "resumable": "yellow"}
        for r in rows:
            state = str(r["state"])
            colour = "red" if state.startswith("failed") else colours.get(state, "white")
            table.add_row(r["name"], f"[{colour}]{state}[/{colour}]",
                          f"{r['done']:,}/{r['total']:,} ({100 * r['done'] / max(r['total'], 1):.0f}%)",
                          "-" if r["fps"] is None else f"{r['fps']:.0f}", _pct(r["eval"]), _pct(r["heldout"]))
        self.live.update(table)


def make_view():
    return LiveView() if sys.stdout.isatty() else PlainView()
