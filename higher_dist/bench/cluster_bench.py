"""`higher-bench cluster --seconds S`: the whole system, end to end, on this machine.

Starts `higher-cluster` (the `higher` preset on the paper world by default) as a separate process
tree, waits for learning to start and the learner's loss to be compiled (warm-up), then measures over S seconds from the learner's own
metrics: env frames/s, learner updates/s, samples per frame, weights version lag, and the peak RSS of
every role (sampled with psutil). `learner_ratio` divides the cluster's updates/s by the learner alone
on a synthetic replay at the same batch size (`higher-bench learner`), measured in the same run.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import psutil

from higher_dist.launch.layout import available_cores, plan_layout
from higher_dist.launch.local_cluster import cli_argv
from higher_dist.launch.topology import free_base_port
from higher_dist.learning.devices import resolve_device
from higher_dist.rundir import read_metrics

ROLE_MARKERS = {"learner_main": "learner", "relabeler_main": "relabeler", "actor_main": "actor",
                "dashboard_main": "dashboard"}


def _role_of(proc: psutil.Process) -> str | None:
    try:
        cmd = " ".join(proc.cmdline())
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return None
    return next((role for marker, role in ROLE_MARKERS.items() if marker in cmd), None)


def stop_group(proc: subprocess.Popen, grace_s: float = 60.0) -> None:
    """SIGTERM the cluster's process group (a clean stop: final checkpoints), SIGKILL after `grace_s`."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def _wait_for(path: Path, predicate, timeout: float, proc: subprocess.Popen) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the cluster exited early with code {proc.returncode}; see {path.parent}/logs")
        records = read_metrics(path)
        if records and predicate(records[-1]):
            return records[-1]
        time.sleep(0.5)
    raise TimeoutError(f"no metrics satisfying the warm-up condition within {timeout:.0f} s")


def measure_cluster(seconds: float, preset: str, world: str, actors: int | None, envs: int | None,
                    extra: list[str], warmup_updates: int = 50) -> dict:
    run_dir = Path(tempfile.mkdtemp(prefix="higher-bench-cluster-"))
    args = ["--preset", preset, "--world", world, "--frames", str(10**9), "--no-dashboard",
            "--run-dir", str(run_dir), "--port-base", str(free_base_port()), "--set", "stats_every_s=1.0"]
    if actors:
        args += ["--actors", str(actors)]
    if envs:
        args += ["--envs-per-actor", str(envs)]
    cmd = cli_argv("cluster", *args, *extra)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
    metrics = run_dir / "metrics.jsonl"
    peak: dict[str, int] = {}
    try:
        # Warm-up ends once learning runs and the learner's background compile (dqn.compile) is done.
        start = _wait_for(metrics, lambda r: r.get("updates", 0) >= warmup_updates and not r.get("compile_pending"),
                          900, proc)
        t0 = time.time()
        while time.time() - t0 < seconds:
            for child in psutil.Process(proc.pid).children(recursive=True):
                role = _role_of(child)
                if role:
                    try:
                        peak[role] = max(peak.get(role, 0), child.memory_info().rss)
                    except psutil.NoSuchProcess:
                        pass
            time.sleep(0.5)
        records = read_metrics(metrics)
        end = records[-1]
        lags = [r["weights_lag_mean"] for r in records
                if r["time"] > start["time"] and r.get("weights_lag_mean") is not None]
    finally:
        stop_group(proc)
    dt = end["time"] - start["time"]
    frames = end["frames"] - start["frames"]
    updates = end["updates"] - start["updates"]
    config = json.loads((run_dir / "config.json").read_text())
    batch = config["dqn"]["batch_size"]
    layout = plan_layout(available_cores(), config["actors"], str(resolve_device(config["device"])),
                         config["torch_threads"])
    return {
        "preset": preset, "world": world, "seconds": round(dt, 1), "actors": config["actors"],
        "layout": end.get("layout"), "learner_threads": layout.learner_threads,
        "envs_per_actor": config["envs_per_actor"], "batch_size": batch,
        "frames_per_s": round(frames / dt, 1), "updates_per_s": round(updates / dt, 2),
        # A recurrent learner's update trains whole episodes (a varying count): read the learner's own ratio.
        "samples_per_frame": (end.get("replay_ratio") if config["network"]["core"] == "gru"
                              else round(updates * batch / max(frames, 1), 2)),
        "samples_per_insert_target": config["replay"]["samples_per_insert"],
        "weights_lag_updates": round(sum(lags) / len(lags), 1) if lags else None,
        "peak_rss_mib": {role: round(rss / 2**20) for role, rss in sorted(peak.items())},
        "rejected_messages": end.get("rejected_messages"), "run_dir": str(run_dir),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-bench cluster", description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0, help="measurement window after warm-up")
    p.add_argument("--preset", default="higher")
    p.add_argument("--world", default="paper")
    p.add_argument("--actors", type=int, default=None)
    p.add_argument("--envs-per-actor", type=int, default=None)
    p.add_argument("--learner-seconds", type=float, default=5.0, help="learner-alone measurement per batch")
    p.add_argument("extra", nargs="*", help="more higher-cluster flags, after --")
    args = p.parse_args(argv)
    result = measure_cluster(args.seconds, args.preset, args.world, args.actors, args.envs_per_actor, args.extra)
    from higher_dist.bench.learner_bench import measure_updates_per_s

    # The learner alone on as many threads as the cluster's layout gave it: the ratio is then the cost of
    # the system around the learner, not of a different thread count.
    from higher_dist.config import from_dict

    run_cfg = from_dict(json.loads((Path(result["run_dir"]) / "config.json").read_text()))
    alone = measure_updates_per_s(result["batch_size"], args.learner_seconds, cfg=run_cfg,
                                  threads=result["learner_threads"])
    result["learner_alone_updates_per_s"] = round(alone, 2)
    result["learner_ratio"] = round(result["updates_per_s"] / alone, 3) if alone else None
    print(f"cluster benchmark: preset {result['preset']} on the {result['world']} world, "
          f"{result['actors']} actors x {result['envs_per_actor']} envs, {result['seconds']} s after warm-up")
    rows = [("env frames/s", result["frames_per_s"]), ("learner updates/s", result["updates_per_s"]),
            ("samples per frame", f"{result['samples_per_frame']} (target {result['samples_per_insert_target']})"),
            ("learner alone updates/s", result["learner_alone_updates_per_s"]),
            ("learner_ratio", result["learner_ratio"]), ("weights lag (updates)", result["weights_lag_updates"]),
            ("rejected messages", result["rejected_messages"])]
    rows += [(f"peak RSS {role} (MiB)", mib) for role, mib in result["peak_rss_mib"].items()]
    for name, value in rows:
        print(f"{name:<28}{value}")
    print(json.dumps(result))
    return 0
