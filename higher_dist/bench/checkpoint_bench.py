"""`higher-bench checkpoint`: the learner's checkpoint at the paper world's replay capacity, its size on disk
and the pause it causes.

The learner writes its checkpoint on its own thread (`Learner.checkpoint`: the state, replay included,
copied and saved with fsync), so the pause is the whole write; a resume pays the load. Both are timed here
on a Learner whose replay is full of random but valid episodes, written to a real file in `--dir`
(default: a temp folder on the disk the run folder would use). Prints a table and a JSON line.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def measure(capacity: int | None, repeat: int, directory: Path) -> dict:
    import torch

    from higher_dist.bench.learner_bench import fill_replay
    from higher_dist.config import override
    from higher_dist.config_presets import make_config
    from higher_dist.learning.learner import Learner
    from higher_dist.rundir import RunDir

    torch.set_num_threads(1)
    cfg = make_config("higher", "paper")
    if capacity is not None:
        cfg = override(cfg, **{"replay.capacity": capacity})
    core = Learner(cfg)
    fill_replay(core.replay, cfg.world.max_steps)
    rd = RunDir(directory)
    state_s, save_s, load_s = [], [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        state = {"core": core.state_dict(with_replay=True), "weights_version": 0,
                 "torch_rng": torch.get_rng_state(), "elapsed_s": 0.0, "config": cfg.to_dict()}
        t1 = time.perf_counter()
        path = rd.save_checkpoint("learner", state)
        t2 = time.perf_counter()
        loaded = rd.load_checkpoint("learner")
        Learner(cfg).load_state_dict(loaded["core"])  # the resume's own work: copied into a fresh core
        t4 = time.perf_counter()
        del state, loaded
        state_s.append(t1 - t0)
        save_s.append(t2 - t1)
        load_s.append(t4 - t2)
    size = path.stat().st_size
    without = {"core": core.state_dict(with_replay=False), "config": cfg.to_dict()}
    small = rd.save_checkpoint("learner-no-replay", without).stat().st_size
    median = lambda xs: float(np.median(xs))  # noqa: E731
    return {"capacity": cfg.replay.capacity, "transitions": len(core.replay), "size_mib": round(size / 2**20, 1),
            "size_without_replay_mib": round(small / 2**20, 2), "snapshot_s": round(median(state_s), 3),
            "write_s": round(median(save_s), 3), "pause_s": round(median(state_s) + median(save_s), 3),
            "resume_load_s": round(median(load_s), 3), "repeat": repeat}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="higher-bench checkpoint", description=__doc__.splitlines()[0])
    p.add_argument("--capacity", type=int, default=None, help="replay capacity (default: the paper world's)")
    p.add_argument("--repeat", type=int, default=3, help="writes and loads timed (the median is printed)")
    p.add_argument("--dir", default=None, help="where the checkpoint is written (default: a temp folder)")
    args = p.parse_args(argv)
    if args.repeat < 1 or (args.capacity is not None and args.capacity < 1000):
        p.error("--repeat must be >= 1 and --capacity >= 1000")
    with tempfile.TemporaryDirectory(prefix="higher-ckpt-", dir=args.dir) as tmp:
        r = measure(args.capacity, args.repeat, Path(tmp))
    print(f"learner checkpoint, replay of {r['transitions']:,} transitions (capacity {r['capacity']:,}), "
          f"median of {r['repeat']}")
    print(f"{'size on disk':<34}{r['size_mib']:>10} MiB   (without the replay {r['size_without_replay_mib']} MiB)")
    print(f"{'snapshot (state copied)':<34}{r['snapshot_s']:>10} s")
    print(f"{'write (torch.save, fsync, rename)':<34}{r['write_s']:>10} s")
    print(f"{'pause of the learner':<34}{r['pause_s']:>10} s")
    print(f"{'resume (load into a fresh core)':<34}{r['resume_load_s']:>10} s")
    print(json.dumps(r))
    return 0
