"""Learner speed: DQN updates/s and samples/s at batch 64, 128, 256 on synthetic batches.

Each update is the full learner step (online forward on obs, online and target forwards on next_obs,
backward, gradient clipping, Adam, target update) on random but valid views and missions prepared
ahead, so the figure measures the network and optimizer, not batch generation or the replay.
Alongside wall-clock rates it reports CPU time per update: on a shared machine the wall figure
moves with the neighbours' load, the CPU figure much less. The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from types import SimpleNamespace

import numpy as np
import torch

from higher_dist.config import DQNConfig, NetworkConfig
from higher_dist.learning.dqn import DQNLearner
from higher_dist.learning.networks import count_parameters
from higher_dist.world.spec import DEFAULT_SPEC, VIEW_CHANNEL_VALUES

BATCH_SIZES = (64, 128, 256)
VOCAB_SIZE = DEFAULT_SPEC.vocab_size
MISSION_LEN = 10
_POOL = 8  # distinct batches cycled per size: varied inputs without generation inside the timing


def synthetic_batch(rng: np.random.Generator, batch_size: int, frame_stack: int, view_size: int = 7,
                    gamma: float = 0.99, n_step: int = 3) -> SimpleNamespace:
    """A TransitionBatch look-alike: object cells carry attributes, other cells zeros; missions of
    6..8 words (the real prefixes' range) padded with PAD; a third of the windows terminal."""
    def views() -> np.ndarray:
        shape = (batch_size, frame_stack, view_size, view_size)
        out = np.zeros(shape + (4,), np.uint8)
        kind = rng.choice(5, size=shape, p=[0.3, 0.5, 0.1, 0.05, 0.05])
        out[..., 0] = kind
        for ch in (1, 2, 3):
            out[..., ch] = np.where(kind >= 3, rng.integers(1, VIEW_CHANNEL_VALUES[ch], shape), 0)
        return out

    mission = np.zeros((batch_size, MISSION_LEN), np.int64)
    for i, n in enumerate(rng.integers(6, 9, batch_size)):
        mission[i, :n] = rng.integers(3, VOCAB_SIZE, n)
    terminal = rng.random(batch_size) < 1 / 3
    return SimpleNamespace(
        indices=np.arange(batch_size, dtype=np.int64), generations=np.zeros(batch_size, np.int64),
        obs=views(), mission=mission, action=rng.integers(0, 4, batch_size),
        reward=(terminal & (rng.random(batch_size) < 0.5)).astype(np.float32),
        discount=np.where(terminal, 0.0, gamma ** n_step).astype(np.float32), next_obs=views(),
        weights=rng.uniform(0.3, 1.0, batch_size).astype(np.float32),
    )


def measure(learner: DQNLearner, batches: list[SimpleNamespace], seconds: float, warmup: int) -> dict[str, float]:
    for i in range(warmup):
        learner.update(batches[i % len(batches)])
    n = 0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    while True:
        learner.update(batches[n % len(batches)])
        n += 1
        wall = time.perf_counter() - wall0
        if wall >= seconds:
            break
    cpu = time.process_time() - cpu0
    b = len(batches[0].action)
    return {"updates_per_s": n / wall, "samples_per_s": n * b / wall, "ms_per_update": 1e3 * wall / n,
            "cpu_ms_per_update": 1e3 * cpu / n, "cpu_samples_per_s": n * b / cpu, "updates": n}


def _parse_override(text: str) -> tuple[str, object]:
    """`name=value` for a NetworkConfig field; tuples as comma lists (conv_channels=16,32)."""
    name, _, value = text.partition("=")
    fields = {f.name: f for f in dataclasses.fields(NetworkConfig)}
    if name not in fields or not value:
        raise argparse.ArgumentTypeError(f"--net expects FIELD=VALUE with FIELD in {sorted(fields)}")
    default = getattr(NetworkConfig(), name)
    if isinstance(default, tuple):
        return name, tuple(int(v) for v in value.split(",") if v)
    if isinstance(default, bool):
        return name, value.lower() in ("1", "true", "yes")
    if isinstance(default, int):
        return name, int(value)
    return name, value


def synthetic_episode(rng: np.random.Generator, length: int, view_size: int = 7):
    """A random but valid episode (view values in range, a mission of words) for filling a replay."""
    from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode

    maxima = np.array([5, 7, 6, 6])
    frames = (rng.random((length + 1, view_size, view_size, 4)) * maxima).astype(np.uint8)
    outcome = int(rng.choice([SUCCESS, WRONG_PICK, TIMEOUT]))
    rewards = np.zeros(length, np.float32)
    rewards[-1] = 1.0 if outcome == SUCCESS else 0.0
    from higher_dist.world.language import VOCAB

    words = rng.integers(3, len(VOCAB), size=int(rng.integers(5, 9)))
    mission = np.zeros(10, np.int64)
    mission[: words.size] = words
    return Episode(frames=frames, actions=rng.integers(0, 4, length).astype(np.uint8), rewards=rewards,
                   mission=mission, outcome=outcome, picked=np.full(4, -1, np.int8), goal=np.zeros(4, np.int8))


def measure_updates_per_s(batch_size: int, seconds: float = 5.0, cfg=None, warmup: int = 5) -> float:
    """Updates/s of the learner alone, through the same path as in the cluster (LearnerCore.update:
    prioritized sampling from a full replay, the DQN step, the priority update)."""
    from higher_dist.config import make_config, override
    from higher_dist.learning.learner_core import LearnerCore

    cfg = cfg or make_config("higher", "paper")
    cfg = override(cfg, **{"dqn.batch_size": batch_size, "replay.capacity": 100_000})
    torch.set_num_threads(cfg.torch_threads)
    core = LearnerCore(cfg)
    rng = np.random.default_rng(0)
    pool = [synthetic_episode(rng, int(rng.integers(5, cfg.world.max_steps + 1))) for _ in range(64)]
    added = 0
    while added < cfg.replay.capacity:
        episode = pool[int(rng.integers(len(pool)))]
        core.replay.add_episode(episode)
        added += episode.length
    for _ in range(warmup):
        core.update()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        core.update()
        n += 1
    return n / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="higher-bench learner", description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per batch size")
    parser.add_argument("--warmup", type=int, default=10, help="untimed updates per batch size")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--batch-sizes", default=",".join(map(str, BATCH_SIZES)))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--net", type=_parse_override, action="append", default=[], metavar="FIELD=VALUE",
                        help="override a NetworkConfig field, e.g. --net embed_dim=8 --net conv_channels=16,32")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    net_cfg = dataclasses.replace(NetworkConfig(), **dict(args.net))
    dqn_cfg = DQNConfig()
    sizes = [int(s) for s in args.batch_sizes.split(",") if s]
    rng = np.random.default_rng(args.seed)

    params = count_parameters(DQNLearner(net_cfg, dqn_cfg, device=args.device).online)
    print(f"learner bench: {args.threads} thread(s), device {args.device}, torch {torch.__version__}, "
          f"{params} parameters")
    print(f"network: {dataclasses.asdict(net_cfg)}")
    print(f"{'batch':>6} {'updates/s':>10} {'samples/s':>10} {'ms/update':>10} {'cpu ms/upd':>11} {'cpu samples/s':>14}")
    summary: dict[str, object] = {"threads": args.threads, "device": args.device, "parameters": params,
                                  "network": dataclasses.asdict(net_cfg)}
    for b in sizes:
        # A fresh learner per size: Adam state and target schedule start alike for every row.
        learner = DQNLearner(net_cfg, dqn_cfg, device=args.device, seed=args.seed)
        batches = [synthetic_batch(rng, b, net_cfg.frame_stack, gamma=dqn_cfg.gamma, n_step=dqn_cfg.n_step)
                   for _ in range(_POOL)]
        r = measure(learner, batches, args.seconds, args.warmup)
        print(f"{b:>6} {r['updates_per_s']:>10.1f} {r['samples_per_s']:>10.0f} {r['ms_per_update']:>10.2f} "
              f"{r['cpu_ms_per_update']:>11.2f} {r['cpu_samples_per_s']:>14.0f}")
        summary[f"b{b}_updates_per_s"] = round(r["updates_per_s"], 1)
        summary[f"b{b}_samples_per_s"] = round(r["samples_per_s"], 0)
        summary[f"b{b}_cpu_samples_per_s"] = round(r["cpu_samples_per_s"], 0)
    if args.device == "cpu" and not args.net:
        # The same, through the full learner path: sampling a full prioritized replay and updating
        # priorities. This is the ceiling the cluster's learner_ratio is measured against.
        print("with a full prioritized replay (sample + update + priorities), default config:")
        for b in sizes:
            ups = measure_updates_per_s(b, args.seconds)
            print(f"{b:>6} {ups:>10.1f} {ups * b:>10.0f}")
            summary[f"replay_b{b}_updates_per_s"] = round(ups, 1)
            summary[f"replay_b{b}_samples_per_s"] = round(ups * b, 0)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
