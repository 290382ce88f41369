"""`higher-bench gpu` (`make bench-gpu`): the learner on a CUDA device and the whole cluster around it.

Two measurements, in under 5 minutes on a GPU host, ending with one JSON line:
- the learner alone (`Learner.update` on a full synthetic replay: prioritized sampling on the host,
  the batch through pinned buffers to the device, the DQN step there, priorities back), eager at each
  `--batch-sizes` and compiled at the default batch;
- `higher-cluster` with the host's default layout (`launch/layout.py`: a GPU learner leaves every core
  but three to actors) or `--actors N`, env frames/s and updates/s over `--cluster-seconds`.
Without a CUDA device it refuses (exit 2), unless `--allow-cpu` runs the same path on the CPU (the
fallback the tests cover).
"""
from __future__ import annotations

import argparse
import json
import time

import torch

from higher_dist.bench.cluster_bench import measure_cluster
from higher_dist.bench.learner_bench import Lever, make_core, time_updates
from higher_dist.config_flags import DefaultsHelp
from higher_dist.config_presets import make_config
from higher_dist.launch.layout import available_cores, plan_layout
from higher_dist.learning.devices import resolve_device


def learner_rows(device: str, sizes: list[int], seconds: float, compiled: bool, threads: int) -> dict:
    rows = {}
    default_batch = make_config("her", "paper").dqn.batch_size
    levers = [Lever("eager")] + ([Lever("compiled", compile=True)] if compiled else [])
    for lever in levers:
        for b in sizes if lever.name == "eager" else [default_batch]:
            cfg = make_config("her", "paper", device=device)
            core, compile_s = make_core(b, lever, cfg, threads=threads)
            try:
                r = time_updates(core, seconds, warmup=10)
            finally:
                core.close()
            rows[f"{lever.name} b{b}"] = {"samples_per_s": round(r["samples_per_s"]),
                                          "updates_per_s": round(r["updates_per_s"], 1),
                                          "compile_s": None if compile_s is None else round(compile_s, 1)}
            print(f"learner {lever.name:<9} B={b:<6}{r['samples_per_s']:>12,.0f} samples/s"
                  + (f"   (compile {compile_s:.0f} s)" if compile_s else ""), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-bench gpu", description=__doc__.splitlines()[0],
                                formatter_class=DefaultsHelp)
    p.add_argument("--batch-sizes", default="256,1024", help="eager learner rows, comma-separated")
    p.add_argument("--seconds", type=float, default=5.0, help="timed seconds per learner row")
    p.add_argument("--no-compile", action="store_true", help="skip the compiled learner row")
    p.add_argument("--cluster-seconds", type=float, default=60.0, help="cluster window after warm-up (0: skip)")
    p.add_argument("--actors", type=int, default=None, help="actors of the cluster (default: the layout's)")
    p.add_argument("--allow-cpu", action="store_true", help="without a CUDA device, measure the CPU instead")
    args = p.parse_args(argv)
    device = str(resolve_device("auto"))
    if device == "cpu" and not args.allow_cpu:
        print("higher-bench gpu: error: torch sees no CUDA device on this host "
              "(run it on a GPU host, or add --allow-cpu to measure the CPU path)", flush=True)
        return 2
    try:
        sizes = [int(s) for s in args.batch_sizes.split(",") if s]
    except ValueError:
        p.error(f"--batch-sizes: expected comma-separated integers, got {args.batch_sizes!r}")
    if not sizes or min(sizes) < 1 or args.seconds <= 0 or args.cluster_seconds < 0:
        p.error("--batch-sizes, --seconds must be positive and --cluster-seconds >= 0")
    cores = available_cores()
    layout = plan_layout(cores, args.actors, device)
    name = torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu"
    print(f"gpu bench: {name}, {cores} cores, torch {torch.__version__}; layout {layout.describe()}", flush=True)
    t0 = time.time()
    result: dict = {"device": device, "device_name": name, "cores": cores, "layout": layout.to_dict(),
                    "learner": learner_rows(device, sizes, args.seconds, not args.no_compile, layout.learner_threads)}
    if args.cluster_seconds > 0:
        cluster = measure_cluster(args.cluster_seconds, "her", "paper", layout.actors, None, ["--device", device])
        result["cluster"] = {k: cluster[k] for k in ("frames_per_s", "updates_per_s", "samples_per_frame", "actors",
                                                    "envs_per_actor", "batch_size", "seconds")}
        print(f"cluster: {cluster['frames_per_s']:,.0f} env frames/s, {cluster['updates_per_s']:.1f} updates/s with "
              f"{cluster['actors']} actors x {cluster['envs_per_actor']} envs", flush=True)
    result["bench_wall_s"] = round(time.time() - t0, 1)
    print(json.dumps(result))
    return 0
