"""The trigger experiment per run: how fast the generator's dataset grows and when relabelling begins.

The trigger's verdict (claims.py) compares end points; this table shows what the trigger really moves.
Before any relabel the generator's only positive pairs are the agent's own successes, so a run waiting
for 1000 or 2000 pairs depends on how often its exploring policy succeeds (`success_rate_train`). Read
from each run's records:
- pairs: `relabel_dataset_size` at CHECKPOINTS (shares of the longest run's budget), from the record
  nearest that frame, "-" past a run's own budget;
- exploring success at SUCCESS_AT of the budget, the same way;
- relabelling began: the first record with `relabel_gate_open`; "at once" within AT_ONCE_FRAMES; "not
  by F" where F is the run's last record.
An archived run keeps one record per 10k frames, so a frame read from the archive is up to 10k late.
"""
from __future__ import annotations

import numpy as np

from higher_dist import metrics as m
from higher_dist.analysis.runs import Run

CHECKPOINTS = (0.1, 0.2, 0.4, 0.6, 0.8, 1.0)
SUCCESS_AT = (0.1, 0.4, 1.0)
AT_ONCE_FRAMES = 10_000

CAPTION = ("Pairs in the generator's dataset, the exploring policy's success (its episodes' success while "
           "epsilon-greedy) and the frame at which the generator began to relabel, per run.")


def frames_text(frames: float) -> str:
    """100k, 1M, 1.5M: a frame count as the table's columns name it."""
    if frames >= 1e6:
        return f"{frames / 1e6:g}M"
    return f"{frames / 1e3:g}k"


def _budget(run: Run) -> float | None:
    """The run's own frame budget, as its records state it (None where they do not)."""
    return next((float(r[m.FRAMES_BUDGET]) for r in run.records if r.get(m.FRAMES_BUDGET)), None)


def _at(run: Run, key: str, frames: float) -> float | None:
    """The value of `key` in the record whose frames are nearest `frames`; None past the run's own budget
    (a 1M run in a table of 2M runs has no 1.6M)."""
    x, y = run.series(key)
    budget = _budget(run)
    if len(x) == 0 or (budget is not None and frames > budget * 1.001):
        return None
    return float(y[int(np.argmin(np.abs(x - frames)))])


def gate_opened(run: Run) -> float | None:
    """The frame of the first record in which the generator relabels."""
    return next((float(r[m.FRAMES]) for r in run.records if r.get(m.RELABEL_GATE_OPEN) and m.FRAMES in r), None)


def _began(run: Run) -> str:
    frames = gate_opened(run)
    if frames is None:  # by the run's own last record: a run still going has not reached the budget
        last = max((float(r[m.FRAMES]) for r in run.records if m.FRAMES in r), default=0.0)
        return f"not by {frames_text(round(last, -4))}"
    return "at once" if frames <= AT_ONCE_FRAMES else frames_text(frames // 1000 * 1000)


def table(groups: dict[int, list[Run]], budget: float) -> list[str]:
    """One row per (trigger, seed); `groups` maps a trigger's pair count to its runs."""
    if not any(groups.values()):
        return []
    points = [p * budget for p in CHECKPOINTS]
    success_at = ", ".join(frames_text(p * budget) for p in SUCCESS_AT)
    lines = [f"| trigger | seed | pairs at {frames_text(points[0])} frames | "
             + " | ".join(frames_text(p) for p in points[1:])
             + f" | exploring success at {success_at} | relabelling began |",
             "| " + " | ".join(["---"] * (len(points) + 4)) + " |"]
    for pairs, runs in sorted(groups.items()):
        for run in sorted(runs, key=lambda r: str(r.seed)):
            counts = [_at(run, m.RELABEL_DATASET_SIZE, p) for p in points]
            success = [_at(run, m.SUCCESS_TRAIN, p * budget) for p in SUCCESS_AT]
            lines.append(f"| {pairs} pairs | {run.seed} | "
                         + " | ".join("-" if c is None else f"{c:,.0f}" for c in counts) + " | "
                         + ", ".join("-" if s is None else f"{100 * s:.0f}%" for s in success)
                         + f" | {_began(run)} |")
    return lines

