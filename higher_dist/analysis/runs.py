"""Runs as the analysis reads them: a run folder's config.json and metrics.jsonl, the curves in it.

A folder without metrics.jsonl but with run subfolders (runs/ holding runs/a, runs/b) stands for those
runs. Records are read as written (see docs/metrics.md for the keys); a value that is not a finite
number is no point of a curve.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from higher_dist import metrics as m

GRID_POINTS = 200  # points of the common frames grid that seeds' curves are interpolated onto
REPLAY_KEYS = (("replay_success", "success", "tab:green"), ("replay_wrong_pick", "wrong pick", "tab:red"),
               ("replay_timeout", "time-out", "tab:olive"), ("replay_relabelled", "relabelled", "tab:cyan"))
# The results of one greedy evaluation: a record carrying a number under any of them carries an evaluation.
EVALUATION_KEYS = (m.SUCCESS_EVAL_TRAIN, m.SUCCESS_EVAL_HELDOUT, m.SUCCESS_EVAL_TRAIN_AVERAGED,
                   m.SUCCESS_EVAL_HELDOUT_AVERAGED)


class NoRun(Exception):
    """A directory given on the command line holds no run."""


@dataclass(frozen=True)
class Evaluation:
    """One greedy evaluation of a run: the env frames its weights had seen, and the first record that
    carried it (whose elapsed_s, updates, ... are those of the moment its result came out)."""
    frames: int
    record: dict[str, Any]

    def value(self, key: str) -> float | None:
        v = self.record.get(key)
        return float(v) if is_number(v) else None


@dataclass
class Run:
    path: Path
    preset: str
    seed: Any
    world: str
    records: list[dict[str, Any]] = field(default_factory=list)

    @property
    def label(self) -> str:
        return f"{self.preset} seed {self.seed}" if self.seed is not None else f"{self.preset} ({self.path.name})"

    def series(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """(frames, values) for the records where both are numbers, sorted by frames."""
        pts = [(r.get(m.FRAMES), r.get(key)) for r in self.records]
        pts = [(float(f), float(v)) for f, v in pts if is_number(f) and is_number(v)]
        pts.sort()
        if not pts:
            return np.empty(0), np.empty(0)
        arr = np.asarray(pts)
        return arr[:, 0], arr[:, 1]

    def evaluations(self) -> list[Evaluation]:
        """Each greedy evaluation once, sorted by its frames. Every record repeats the latest evaluation, so:
        - a record whose evaluation (EVAL_FRAMES and EVALUATION_KEYS' values) equals that of the evaluation
          record before it repeats that evaluation, which keeps its first record;
        - an evaluation's frames are its EVAL_FRAMES; records without them (the single-process runner's,
          which evaluates right before it records) are counted at their own frames;
        - of several evaluations at one frame count, the last one kept: a run resumed from a checkpoint
          records again the frames after it and evaluates them again, and only those later results belong
          to the run that goes on (the earlier ones are of the weights the resume threw away)."""
        by_frames: dict[int, Evaluation] = {}
        previous = None
        for r in self.records:
            values = tuple(r.get(k) if is_number(r.get(k)) else None for k in EVALUATION_KEYS)
            if values == (None,) * len(values):
                continue
            identity = (r.get(m.EVAL_FRAMES), values)
            if identity == previous:
                continue
            previous = identity
            frames = r.get(m.EVAL_FRAMES) if is_number(r.get(m.EVAL_FRAMES)) else r.get(m.FRAMES)
            if is_number(frames):
                by_frames[int(frames)] = Evaluation(int(frames), r)
        return [by_frames[f] for f in sorted(by_frames)]

    def has(self, key: str) -> bool:
        return any(is_number(r.get(key)) for r in self.records)


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def load_run(path: Path) -> Run:
    from higher_dist.rundir import read_metrics  # imports torch: only pay for it once we have a run

    metrics = path / "metrics.jsonl"
    if not metrics.is_file():
        raise NoRun(f"higher-plot: {path} holds no run (no metrics.jsonl)")
    records = [r for r in read_metrics(metrics) if isinstance(r, dict)]
    if not records:
        raise NoRun(f"higher-plot: {path} holds no run (metrics.jsonl has no records)")
    config: dict[str, Any] = {}
    try:
        config = json.loads((path / "config.json").read_text())
    except (OSError, json.JSONDecodeError):
        pass  # an interrupted run may lack it; the records carry preset and world too
    world = config.get("world")
    world_name = world.get("name") if isinstance(world, dict) else records[-1].get(m.WORLD)
    preset = config.get("preset") or records[-1].get(m.PRESET) or path.name
    return Run(path, str(preset), config.get("seed"), str(world_name or "-"), records)


def find_runs(paths: list[str]) -> list[Run]:
    runs = []
    for p in map(Path, paths):
        if not (p / "metrics.jsonl").is_file() and p.is_dir():
            children = sorted(c for c in p.iterdir() if (c / "metrics.jsonl").is_file())
            if children:
                runs.extend(load_run(c) for c in children)
                continue
        runs.append(load_run(p))
    return runs


def success_key(run: Run) -> str:
    """Greedy evaluation on training goals when the run has it; otherwise the training success."""
    return m.SUCCESS_EVAL_TRAIN if run.has(m.SUCCESS_EVAL_TRAIN) else m.SUCCESS_TRAIN


def mean_band(curves: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(grid, mean, min, max) of several seeds' curves over the frames they all cover, or None."""
    curves = [(x, y) for x, y in curves if len(x) > 0]
    if not curves:
        return None
    start, stop = max(x[0] for x, _ in curves), min(x[-1] for x, _ in curves)
    if stop <= start:
        return None  # no common range: interpolating would be extrapolation
    grid = np.linspace(start, stop, GRID_POINTS)
    ys = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, ys.mean(axis=0), ys.min(axis=0), ys.max(axis=0)


def replay_fractions(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(frames, fractions[4, T]) of the replay's origins, for records that report them."""
    frames, rows = [], []
    for r in sorted((r for r in run.records if is_number(r.get(m.FRAMES))), key=lambda r: r[m.FRAMES]):
        counts = [r.get(k) for k, _, _ in REPLAY_KEYS]
        if not any(is_number(c) for c in counts):
            continue
        counts = [float(c) if is_number(c) and c > 0 else 0.0 for c in counts]
        total = sum(counts)
        if total > 0:
            frames.append(float(r[m.FRAMES]))
            rows.append([c / total for c in counts])
    if not rows:
        return np.empty(0), np.empty((len(REPLAY_KEYS), 0))
    return np.asarray(frames), np.asarray(rows).T
