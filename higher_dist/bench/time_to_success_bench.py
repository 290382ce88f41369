"""`higher-bench time-to-success --preset her --target 0.4`: how long until the agent is good, here.

Runs the real cluster (`higher-cluster`, every role in its own process, as a user runs it: the
single-process runner would serialise acting and learning on one core and measure a slower system
than the one people use) on the paper world, and watches its metrics: the greedy success rate on
training goals that the learner's periodic evaluation reports (`evaluate_goal_sets`, the run's own
evaluation, on a thread of the learner). It stops at the first evaluation at or above `--target`, or at `--frames-cap` env
frames, or after `--max-minutes`, and reports env frames and wall-clock seconds (from the launch, so
start-up and the learner's background compile count) to 10%, 20% and 40% success and to the target.
One seed per call: run it again with `--seed` for the spread. Takes tens of minutes, so it is not
part of `make bench` (`make bench-time` runs it). The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from higher_dist import metrics as names
from higher_dist.bench.cluster_bench import stop_group
from higher_dist.launch.topology import free_base_port
from higher_dist.rundir import read_metrics

LEVELS = (0.1, 0.2, 0.4)
SUCCESS_KEY = names.SUCCESS_EVAL_TRAIN


def crossings(records: list[dict], levels: list[float], launched: float) -> dict[float, dict]:
    """For each level, the first record whose evaluation reached it: the env frames the evaluated weights
    had seen (`eval_frames`, else the record's frames) and the record's seconds since launch."""
    out: dict[float, dict] = {}
    for r in records:
        value = r.get(SUCCESS_KEY)
        if value is None:
            continue
        for level in levels:
            if level not in out and value >= level:
                out[level] = {"frames": int(r.get(names.EVAL_FRAMES, r["frames"])), "seconds": round(r["time"] - launched, 1),
                              "success": round(float(value), 3)}
    return out


def run(preset: str, world: str, target: float, frames_cap: int, max_minutes: float, seed: int,
        eval_every: int, eval_episodes: int, extra: list[str], poll_s: float = 2.0) -> dict:
    run_dir = Path(tempfile.mkdtemp(prefix=f"higher-time-{preset}-"))
    args = ["--preset", preset, "--world", world, "--frames", str(frames_cap), "--seed", str(seed),
            "--no-dashboard", "--run-dir", str(run_dir), "--port-base", str(free_base_port()),
            "--set", f"eval.every_frames={eval_every}", "--set", f"eval.episodes={eval_episodes}", *extra]
    cmd = [sys.executable, "-c", "import sys; from higher_dist.cli import cluster_main as m; sys.exit(m())", *args]
    levels = sorted(set(LEVELS) | {target})
    launched = time.time()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
    metrics = run_dir / "metrics.jsonl"
    reason = "frames cap"
    try:
        while True:
            time.sleep(poll_s)
            records = read_metrics(metrics)
            if target in crossings(records, [target], launched):
                reason = "target reached"
                break
            if proc.poll() is not None:
                reason = "frames cap" if proc.returncode == 0 else f"cluster exited with code {proc.returncode}"
                break
            if time.time() - launched > 60 * max_minutes:
                reason = "time cap"
                break
    finally:
        stop_group(proc)
    records = read_metrics(metrics)
    last = records[-1] if records else {}
    config = json.loads((run_dir / "config.json").read_text()) if (run_dir / "config.json").exists() else {}
    found = crossings(records, levels, launched)
    # Every record repeats the latest evaluation: one entry per evaluation (its frames).
    evals = {int(r.get(names.EVAL_FRAMES, r["frames"])): r[SUCCESS_KEY] for r in records if r.get(SUCCESS_KEY) is not None}
    return {
        "preset": preset, "world": world, "seed": seed, "target": target, "stop": reason,
        "frames": int(last.get("frames", 0)), "seconds": round((last.get("time", launched)) - launched, 1),
        "batch_size": config.get("dqn", {}).get("batch_size"), "actors": config.get("actors"),
        "envs_per_actor": config.get("envs_per_actor"), "compile": config.get("dqn", {}).get("compile"),
        "levels": {f"{level:g}": found.get(level) for level in levels},
        "best_eval": max(evals.values(), default=None), "evaluations": len(evals),
        "load_average": os.getloadavg(), "run_dir": str(run_dir),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-bench time-to-success", description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="her")
    p.add_argument("--world", default="paper")
    p.add_argument("--target", type=float, default=0.4, help="greedy success on training goals to stop at")
    p.add_argument("--frames-cap", type=int, default=2_000_000, help="env frames at most")
    p.add_argument("--max-minutes", type=float, default=60.0, help="wall-clock minutes at most")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-every", type=int, default=25_000, help="env frames between evaluations")
    p.add_argument("--eval-episodes", type=int, default=128, help="episodes per evaluation (per goal set)")
    p.add_argument("extra", nargs="*", help="more higher-cluster flags, after --")
    args = p.parse_args(argv)
    if not 0 < args.target <= 1:
        p.error(f"--target: must be in (0, 1], got {args.target}")
    if args.frames_cap < 1 or args.max_minutes <= 0:
        p.error("--frames-cap and --max-minutes must be positive")
    result = run(args.preset, args.world, args.target, args.frames_cap, args.max_minutes, args.seed,
                 args.eval_every, args.eval_episodes, args.extra)
    print(f"time to success: preset {result['preset']} on the {result['world']} world, seed {result['seed']}, "
          f"batch {result['batch_size']}, {result['actors']} actor(s) x {result['envs_per_actor']} envs, "
          f"compile {result['compile']}; stopped: {result['stop']} at {result['frames']:,} frames, "
          f"{result['seconds'] / 60:.1f} min")
    print(f"{'greedy success (train goals)':<30}{'env frames':>12}{'minutes':>10}")
    for level, hit in result["levels"].items():
        where = (f"{hit['frames']:>12,}{hit['seconds'] / 60:>10.1f}" if hit else f"{'not reached':>22}")
        print(f"{float(level):<30.0%}{where}")
    print(json.dumps(result))
    return 0
