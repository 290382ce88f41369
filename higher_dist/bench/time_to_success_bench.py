"""`higher-bench time-to-success --preset her --targets 0.4 0.6 --seeds 0 1`: minutes to a learned agent, here.

Runs the real cluster (`higher-cluster`, every role in its own process, as a user runs it) on the paper
world, one seed after another, and reads its metrics. A level X counts as reached at the first greedy
evaluation whose mean with the two evaluations before it is at least X (training goals, online weights:
the unbiased evaluation that the learner runs on its own thread), so a single lucky evaluation does not
count. It is timed by the run's own `elapsed_s` (from the learner's start: compile and warm-up count) and
by the env frames the evaluated weights had seen. The averaged weights' crossing of the same criterion
is reported beside it. A run stops once every target is reached, or at `--frames-cap` env frames, or
after `--max-minutes`. The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from higher_dist import metrics as names
from higher_dist.analysis.runs import Run
from higher_dist.rundir import read_metrics
from higher_dist.bench.cluster_bench import stop_group
from higher_dist.config_flags import DefaultsHelp
from higher_dist.launch.local_cluster import cli_argv
from higher_dist.launch.topology import free_base_port

WINDOW = 3  # an evaluation and the two before it
SUCCESS_KEYS = {"online": names.SUCCESS_EVAL_TRAIN, "averaged": names.SUCCESS_EVAL_TRAIN_AVERAGED}


def evaluations(records: list[dict], key: str = names.SUCCESS_EVAL_TRAIN) -> list[dict]:
    """One entry per evaluation that scored `key`, each once and in order of frames (Run.evaluations): its
    frames (those the evaluated weights had seen), its success, and the run's elapsed seconds at the first
    record that carried it."""
    run = Run(path=Path(), preset="", seed=None, world="", records=records)  # only its records are read
    return [{"frames": e.frames, "success": e.value(key), "seconds": float(e.record.get(names.ELAPSED_S, 0.0))}
            for e in run.evaluations() if e.value(key) is not None]


def crossings(records: list[dict], levels: list[float], key: str = names.SUCCESS_EVAL_TRAIN,
              window: int = WINDOW) -> dict[float, dict]:
    """For each level, the first evaluation at which the mean of the last `window` evaluations (fewer at
    the start never count) is at least the level: {frames, seconds (elapsed_s), success (that mean)}."""
    evals = evaluations(records, key)
    out: dict[float, dict] = {}
    for i in range(window - 1, len(evals)):
        mean = statistics.fmean(e["success"] for e in evals[i - window + 1:i + 1])
        for level in levels:
            if level not in out and mean >= level:
                out[level] = {"frames": evals[i]["frames"], "seconds": evals[i]["seconds"], "success": round(mean, 4)}
    return out


def run(preset: str, world: str, targets: list[float], frames_cap: int, max_minutes: float, seed: int,
        eval_every: int, eval_episodes: int, extra: list[str], poll_s: float = 2.0) -> dict:
    run_dir = Path(tempfile.mkdtemp(prefix=f"higher-time-{preset}-s{seed}-"))
    args = ["--preset", preset, "--world", world, "--frames", str(frames_cap), "--seed", str(seed),
            "--no-dashboard", "--run-dir", str(run_dir), "--port-base", str(free_base_port()),
            "--set", f"eval.every_frames={eval_every}", "--set", f"eval.episodes={eval_episodes}", *extra]
    cmd = cli_argv("cluster", *args)
    launched = time.time()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
    metrics = run_dir / "metrics.jsonl"
    reason = "frames cap"
    try:
        while True:
            time.sleep(poll_s)
            if len(crossings(read_metrics(metrics), targets)) == len(targets):
                reason = "targets reached"
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
    evals = evaluations(records)
    return {
        "preset": preset, "world": world, "seed": seed, "targets": targets, "stop": reason,
        "frames": int(last.get(names.FRAMES, 0)), "seconds": float(last.get(names.ELAPSED_S, 0.0)),
        "frames_per_s": round(int(last.get(names.FRAMES, 0)) / max(float(last.get(names.ELAPSED_S, 0.0)), 1e-9), 1),
        "batch_size": config.get("dqn", {}).get("batch_size"),
        "samples_per_insert": config.get("replay", {}).get("samples_per_insert"),
        "actors": config.get("actors"), "envs_per_actor": config.get("envs_per_actor"),
        "layout": last.get(names.LAYOUT),
        "levels": {weights: {f"{t:g}": crossings(records, targets, key).get(t) for t in targets}
                   for weights, key in SUCCESS_KEYS.items()},
        "best_eval": max((e["success"] for e in evals), default=None), "evaluations": len(evals),
        "last_evals": [round(e["success"], 4) for e in evals[-WINDOW:]],
        "load_average": os.getloadavg(), "run_dir": str(run_dir),
    }


def _cell(hit: dict | None) -> str:
    return f"{hit['seconds'] / 60:>7.1f} min {hit['frames']:>11,}" if hit else f"{'not reached':>23}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-bench time-to-success", description=__doc__.splitlines()[0],
                                formatter_class=DefaultsHelp)
    p.add_argument("--preset", default="her")
    p.add_argument("--world", default="paper")
    p.add_argument("--targets", type=float, nargs="+", default=[0.4, 0.6],
                   help="levels of greedy success on training goals (mean of 3 evaluations)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed, one after another")
    p.add_argument("--frames-cap", type=int, default=3_000_000, help="env frames at most per run")
    p.add_argument("--max-minutes", type=float, default=30.0, help="wall-clock minutes at most per run")
    p.add_argument("--eval-every", type=int, default=25_000, help="env frames between evaluations")
    p.add_argument("--eval-episodes", type=int, default=128, help="episodes per evaluation (per goal set)")
    p.add_argument("extra", nargs="*", help="more higher-cluster flags, after --")
    args = p.parse_args(argv)
    bad = [t for t in args.targets if not 0 < t <= 1]
    if bad:
        p.error(f"--targets: each must be in (0, 1], got {bad}")
    if args.frames_cap < 1 or args.max_minutes <= 0 or args.eval_every < 1 or args.eval_episodes < 1:
        p.error("--frames-cap, --max-minutes, --eval-every and --eval-episodes must be positive")
    targets = sorted(set(args.targets))
    results = []
    for seed in args.seeds:
        r = run(args.preset, args.world, targets, args.frames_cap, args.max_minutes, seed, args.eval_every,
                args.eval_episodes, args.extra)
        results.append(r)
        print(f"seed {seed}: {r['stop']} at {r['frames']:,} frames, {r['seconds'] / 60:.1f} min "
              f"({r['frames_per_s']:,.0f} frames/s; batch {r['batch_size']}, {r['samples_per_insert']} samples per "
              f"insert; {r['layout']})", flush=True)
    print(f"\ntime to success: {args.preset} on the {args.world} world (mean of {WINDOW} greedy evaluations on "
          "training goals, from the run's start)")
    print(f"{'level':<8}{'weights':<10}" + "".join(f"{'seed ' + str(s):>26}" for s in args.seeds))
    for t in targets:
        for weights in SUCCESS_KEYS:
            print(f"{t:<8.0%}{weights:<10}" + "".join(f"{_cell(r['levels'][weights][f'{t:g}']):>26}" for r in results))
    summary = {}
    for t in targets:
        hits = [r["levels"]["online"][f"{t:g}"] for r in results]
        # The slowest seed's figure, or None when a seed did not get there: a bound every seed met.
        summary[f"minutes_to_{round(100 * t)}"] = (round(max(h["seconds"] for h in hits) / 60, 2)
                                                   if all(hits) else None)
        summary[f"frames_to_{round(100 * t)}"] = max(h["frames"] for h in hits) if all(hits) else None
    print(json.dumps({"preset": args.preset, "world": args.world, "targets": targets, **summary, "runs": results}))
    return 0
