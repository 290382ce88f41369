"""The replay's composition set against the paper's: its figure of HIGhER's replay and the text around it.

The paper reports, for DQN+HIGhER on 5M frames: 90% of the transitions negative at the start; 40%
relabelled once the generator runs; 15% relabelled and 60% positive at the end; time-outs 54% on
average. Ours come from the learner's counts of the transitions in its replay by origin (metrics
`replay_success`, `replay_wrong_pick`, `replay_timeout`, `replay_relabelled`):
- negative = wrong picks + time-outs (the original copies of failed episodes); positive = successes;
- "at the start" is the mean over the first START_FRAMES frames; "once the generator runs" is the
  highest relabelled share of the run (it falls afterwards as successes crowd relabels out); "at the
  end" is the mean over the run's last END_SHARE of frames; time-outs are averaged over the run's frames.
  Every mean is over frames, not over records: a run writes records per second, so a slow stretch (the
  first seconds, while the learner compiles) would otherwise weigh more.
A share within CLOSE of the paper's counts as matching it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from higher_dist.analysis.runs import Run, replay_fractions
from higher_dist.reproduce.plan import seeds_text

START_FRAMES = 100_000
END_SHARE = 0.10
CLOSE = 0.10
DEFINITION = (f"Shares of the transitions in the learner's replay, mean +- std over seeds. Negative: the original "
              f"copies of failed episodes (wrong picks and time-outs); positive: successes; at the start: the first "
              f"{START_FRAMES:,} frames; at the end: the run's last {100 * END_SHARE:.0f}% of frames; once the "
              f"generator runs: the run's highest relabelled share. The paper's figures are HIGhER's at 5M frames.")
# (key, what, the paper's share): the measures of one run's replay, in the table's order.
MEASURES = (
    ("negative_start", "negative at the start", 0.90),
    ("relabelled_peak", "relabelled once the generator runs (the run's peak)", 0.40),
    ("relabelled_end", "relabelled at the end", 0.15),
    ("positive_end", "positive at the end", 0.60),
    ("timeout_mean", "time-outs, averaged over the run", 0.54),
)
PAPER = {key: share for key, _, share in MEASURES}
# Rows of replay_fractions: success, wrong pick, time-out, relabelled (analysis.runs.REPLAY_KEYS).
SUCCESS, WRONG, TIMEOUT, RELABELLED = range(4)
# The shares a figure draws, each from replay_fractions' rows.
SHARES = {"negative": lambda f: f[WRONG] + f[TIMEOUT], "positive": lambda f: f[SUCCESS],
          "relabelled": lambda f: f[RELABELLED], "time-outs": lambda f: f[TIMEOUT]}


def run_measures(run: Run) -> dict[str, float] | None:
    """The five shares of one run (and the frames of the relabelled peak and of the run's end)."""
    x, f = replay_fractions(run)
    if len(x) == 0:
        return None
    negative = SHARES["negative"](f)
    start = x <= max(START_FRAMES, x[0])
    end = x >= x[-1] - END_SHARE * (x[-1] - x[0])
    peak = int(np.argmax(f[RELABELLED]))
    return {"negative_start": _frame_mean(x[start], negative[start]),
            "relabelled_peak": float(f[RELABELLED][peak]), "peak_frames": float(x[peak]),
            "relabelled_end": _frame_mean(x[end], f[RELABELLED][end]),
            "positive_end": _frame_mean(x[end], f[SUCCESS][end]),
            "timeout_mean": _frame_mean(x, f[TIMEOUT]), "timeout_end": _frame_mean(x[end], f[TIMEOUT][end]),
            "frames": float(x[-1])}


def _frame_mean(x: np.ndarray, y: np.ndarray) -> float:
    """Mean of y over the frames x spans (trapezoids); one point, or no frames between them: the plain mean."""
    if len(x) < 2 or x[-1] <= x[0]:
        return float(y.mean())
    return float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(x)) / (x[-1] - x[0]))


def group_measures(runs: list[Run]) -> dict | None:
    """key -> (mean, std) over the seeds, with seeds, the fewest frames and the mean peak frames."""
    per_run = [v for v in map(run_measures, runs) if v]
    if not per_run:
        return None
    out = {key: (float(np.mean([v[key] for v in per_run])), float(np.std([v[key] for v in per_run])))
           for key, _, _ in MEASURES}
    out.update(seeds=len(per_run), frames=int(min(v["frames"] for v in per_run)),
               peak_frames=float(np.mean([v["peak_frames"] for v in per_run])),
               timeout_end=float(np.mean([v["timeout_end"] for v in per_run])))
    return out


def replay_capacity(runs: list[Run]) -> int | None:
    for run in runs:
        try:
            return int(json.loads((run.path / "config.json").read_text())["replay"]["capacity"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return None


def _pct(mean_std: tuple[float, float]) -> str:
    return f"{100 * mean_std[0]:.0f}% +- {100 * mean_std[1]:.0f}"


def claim_row(runs: list[Run], label: str) -> dict:
    """The claims table's row for the composition: ours for `label`'s runs against the paper's five shares."""
    paper = "; ".join(f"{what.split(' (')[0]} {100 * share:.0f}%" for _, what, share in MEASURES)
    row = {"claim": "The replay's composition over training (HIGhER)", "paper": paper,
           "rule": f"each share within {100 * CLOSE:.0f} points of the paper's"}
    stats = group_measures(runs)
    if stats is None:
        row["ours"] = "not measured"
        return row
    row["ours"] = ("; ".join(f"{what.split(' (')[0]} {_pct(stats[key])}" for key, what, _ in MEASURES)
                   + f" ({label}, {seeds_text(stats['seeds'])}, {stats['frames']:,} frames)")
    off = [(key, what, share) for key, what, share in MEASURES if abs(stats[key][0] - share) > CLOSE]
    row["verdict"] = "holds" if not off else "partly" if len(off) < len(MEASURES) else "does not hold"
    capacity = replay_capacity(runs) if off else None
    row["why"] = "; ".join(_why(key, stats, share, capacity) for key, _, share in off)
    return row


def _why(key: str, stats: dict, paper: float, capacity: int | None) -> str:
    ours = stats[key][0]
    side = "above" if ours > paper else "below"
    gap = f"{key.replace('_', ' ')} {100 * ours:.0f}% is {abs(100 * (ours - paper)):.0f} points {side} the paper's"
    replay = f"a replay of {capacity:,} transitions, the paper's 50,000" if capacity else "the paper's replay: 50,000"
    reasons = {
        "negative_start": f"over the first {START_FRAMES:,} frames",
        "relabelled_peak": f"peak at {stats['peak_frames']:,.0f} frames, in {replay}",
        "relabelled_end": (f"only failures that picked something are relabelled, each copy ending at its first pick, "
                           f"and time-outs are {100 * stats['timeout_end']:.0f}% of the replay at the end; the "
                           f"paper's end is 5M frames, ours {stats['frames']:,}"),
        "positive_end": (f"the paper's end is 5M frames, ours {stats['frames']:,}, in {replay}; a success is "
                         "shorter than a time-out, so successes' share of transitions is below their share of episodes"),
        "timeout_mean": f"over {stats['frames']:,} frames, the paper's 5M",
    }
    return f"{gap} ({reasons[key]})"


def table(groups: dict[str, list[Run]]) -> list[str]:
    """Markdown: one row per measure, the paper's share and each method's mean +- std over seeds."""
    stats = {label: group_measures(runs) for label, runs in groups.items()}
    stats = {label: s for label, s in stats.items() if s}
    if not stats:
        return []
    head = "| share of the replay's transitions | the paper (HIGhER, 5M frames) | " + " | ".join(
        f"{label} ({seeds_text(s['seeds'])}, {s['frames']:,} frames)" for label, s in stats.items()) + " |"
    lines = [head, "| --- | --- |" + " --- |" * len(stats)]
    for key, what, share in MEASURES:
        lines.append(f"| {what} | {100 * share:.0f}% | " + " | ".join(_pct(s[key]) for s in stats.values()) + " |")
    return lines
