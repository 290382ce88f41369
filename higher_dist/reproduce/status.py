"""Where each run of a plan stands on disk, what the rest will cost on this machine, and the machine itself.

States: `done` (a cluster run whose metrics reached its budget; a generator run with its result.json),
`resumable` (a learner checkpoint: an interrupted run), `stale` (started, but killed before its first
checkpoint: it starts again from nothing), `pending` (never started).

The cost estimate divides the frames left by a frames/s figure, taken from the first of these that
exists, and says which one it used:
1. runs of this plan's folder on the same world (measured here, at the parallelism they ran with);
2. `results/cluster.json` from `make bench` on this machine;
3. a figure below the mean of runs two at a time on the 2-core development machine (docs/benchmarks.md,
   "End to end": 1,330 frames/s per run; 1,100 is used).
A run's learner bounds its frame rate at a fixed samples-per-insert ratio, so a run whose config asks
for more samples per frame is assumed proportionally slower.
"""
from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path

from higher_dist import metrics as m
from higher_dist.reproduce.plan import Plan, RunSpec, default_parallel
from higher_dist.rundir import last_record as _tail_record, read_metrics

FALLBACK_FPS = 1100.0  # docs/benchmarks.md, "End to end": 1,330 frames/s per run on average, two at a time, 2 cores
FALLBACK_SPI = 4.0  # the samples per insert those figures ran at
FALLBACK_GEN_STEPS_PER_S = 35.0  # docs/benchmarks.md: 1500 generator steps in 34-55 s
GEN_OVERHEAD_S = 15.0  # drawing pairs and evaluating, per generator run
MAX_GAP_S = 30.0  # metrics intervals longer than this are a stop and a resume, not running time


def last_record(path: Path) -> dict:
    """A run's newest metrics record, from the file's end: the plan polls every run while it runs, and a
    finished 2M-frame run's metrics hold thousands of records."""
    return _tail_record(path / "metrics.jsonl") or {}


def frames_done(run: RunSpec, path: Path) -> int:
    if run.kind == "generator":
        return run.pairs if (path / "result.json").exists() else 0
    return int(last_record(path).get(m.FRAMES) or 0)


def run_state(run: RunSpec, path: Path) -> str:
    if run.kind == "generator":
        if (path / "result.json").exists():
            return "done"
        return "stale" if path.exists() else "pending"
    if path.exists() and frames_done(run, path) >= run.frames:
        return "done"
    if (path / "learner.ckpt").exists():
        return "resumable"
    return "stale" if path.exists() else "pending"


def measured_fps(path: Path) -> float | None:
    """Frames/s of one run from its metrics: frames over running time, gaps (stops) left out."""
    records = [r for r in read_metrics(path / "metrics.jsonl")
               if isinstance(r.get(m.TIME), (int, float)) and isinstance(r.get(m.FRAMES), (int, float))]
    frames = seconds = 0.0
    for a, b in zip(records, records[1:]):
        dt, df = b[m.TIME] - a[m.TIME], b[m.FRAMES] - a[m.FRAMES]
        if 0 < dt <= MAX_GAP_S and df >= 0:
            frames, seconds = frames + df, seconds + dt
    return frames / seconds if seconds >= 5 and frames > 0 else None


@dataclass
class Rates:
    fps: float  # env frames/s of one run at `spi` samples per insert
    spi: float
    source: str
    gen_steps_per_s: float
    gen_source: str

    def run_seconds(self, run: RunSpec, spi: float, frames_left: int) -> float:
        if run.kind == "generator":
            return 0.0 if frames_left <= 0 else run.steps / self.gen_steps_per_s + GEN_OVERHEAD_S
        return frames_left / (self.fps * self.spi / max(spi, 1e-9))


def rates(plan: Plan, world: str, bench_dir: Path = Path("results")) -> Rates:
    fps = spi = source = None
    measured = []
    for run in plan.runs:
        path = plan.path(run)
        if run.kind == "cluster" and run.world == world and path.exists():
            value = measured_fps(path)
            if value:
                measured.append((value, _spi(path)))
    if measured:
        fps = statistics.median(v for v, _ in measured)
        spi = statistics.median(s for _, s in measured)
        source = (f"measured: median of {len(measured)} run(s) in {plan.out} on the {world} world "
                  f"({fps:.0f} frames/s per run)")
    else:
        bench = _read_json(bench_dir / "cluster.json")
        if bench and bench.get("world") == world and bench.get("frames_per_s"):
            fps, spi = float(bench["frames_per_s"]), float(bench.get("samples_per_insert_target") or FALLBACK_SPI)
            source = f"measured: {bench_dir}/cluster.json from `make bench` on this machine ({fps:.0f} frames/s)"
        else:
            fps, spi = FALLBACK_FPS, FALLBACK_SPI
            source = (f"not measured here: {FALLBACK_FPS:.0f} frames/s, a run of two at a time on the 2-core development "
                      f"machine (docs/benchmarks.md; run `make bench`, or let a plan run, for a figure of this machine)")
    gen = _read_json(bench_dir / "generator.json")
    if gen and gen.get("steps_per_s"):
        gsps, gsource = float(gen["steps_per_s"]), f"{bench_dir}/generator.json ({gen['steps_per_s']} steps/s)"
    else:
        gsps, gsource = FALLBACK_GEN_STEPS_PER_S, f"docs/benchmarks.md ({FALLBACK_GEN_STEPS_PER_S:.0f} steps/s)"
    return Rates(fps, spi, source, gsps, gsource)


def _spi(path: Path) -> float:
    config = _read_json(path / "config.json") or {}
    return float(config.get("replay", {}).get("samples_per_insert") or FALLBACK_SPI)


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return data if isinstance(data, dict) else None


def effective_parallel(parallel: int, n_runs: int) -> float:
    """Runs that really progress at once: at most the plan's default, one per core (the per-run rates are
    measured that way: two runs at a time on the 2-core machine)."""
    return max(1.0, min(parallel, n_runs, default_parallel()))


def estimate(plan: Plan, runs: list[RunSpec], spis: dict[str, float], parallel: int,
             bench_dir: Path = Path("results")) -> tuple[list[dict], float, Rates]:
    """Per run (state, frames left, seconds) and the plan's wall-clock estimate, with the rates used."""
    world = plan.settings.get("world", runs[0].world if runs else "paper")
    r = rates(plan, world, bench_dir)
    rows, total = [], 0.0
    for run in runs:
        path = plan.path(run)
        state = run_state(run, path)
        left = 0 if state == "done" else (run.pairs if run.kind == "generator"
                                          else run.frames - (frames_done(run, path) if state == "resumable" else 0))
        seconds = r.run_seconds(run, spis.get(run.name, FALLBACK_SPI), max(left, 0))
        total += seconds
        rows.append({"run": run, "state": state, "left": max(left, 0), "seconds": seconds})
    todo = sum(1 for row in rows if row["left"] > 0)
    return rows, total / effective_parallel(parallel, max(todo, 1)), r


def human_seconds(s: float) -> str:
    s = max(0.0, float(s))
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    if s < 3 * 86400:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} days"


def run_time(plan: Plan) -> list[str]:
    """One line: the cluster runs' frame rates and minutes per run, measured from their own metrics."""
    fps = {}
    for run in plan.runs:
        if run.kind == "cluster" and (plan.path(run) / "metrics.jsonl").exists():
            value = measured_fps(plan.path(run))
            if value:
                fps[run.name] = (value, frames_done(run, plan.path(run)))
    if not fps:
        return []
    rates = [v for v, _ in fps.values()]
    minutes = [f / v / 60 for v, f in fps.values()]
    return [f"Time: {len(fps)} cluster runs, {plan.settings.get('parallel', 1)} at a time, ran at {min(rates):,.0f}-"
            f"{max(rates):,.0f} env frames/s each, {min(minutes):.0f}-{max(minutes):.0f} minutes per run "
            f"({sum(minutes) / 60:.1f} run-hours in all)."]
