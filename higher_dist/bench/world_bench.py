"""World speed: batched FetchAttr steps/s at B = 1, 64, 256 against Farama MiniGrid's Fetch, same run.

Random uniform actions everywhere; finished episodes reset (in place for the batched world, by
`reset()` for MiniGrid). The last line printed is one JSON object for scripts and CI logs.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from higher_dist.config_presets import world_by_name
from higher_dist.world.grid import N_ACTIONS, BatchedFetchAttr

MINIGRID_ENV_ID = "MiniGrid-Fetch-8x8-N3-v0"
BATCH_SIZES = (1, 64, 256)
_ACTION_ROWS = 1024  # random actions drawn ahead, so the timing measures the world, not the generator
_CLOCK_EVERY = 16  # steps between clock reads


def batched_steps_per_s(world_name: str, batch_size: int, seconds: float, seed: int = 0) -> float:
    """Env steps/s (batch steps x batch size) of the batched world under random actions."""
    env = BatchedFetchAttr(world_by_name(world_name), batch_size, seed=seed)
    env.reset()
    actions = np.random.default_rng(seed).integers(N_ACTIONS, size=(_ACTION_ROWS, batch_size))
    for row in range(32):  # warm-up: first-call costs out of the figure
        env.step(actions[row])
    steps, start = 0, time.perf_counter()
    while True:
        for _ in range(_CLOCK_EVERY):
            env.step(actions[steps % _ACTION_ROWS])
            steps += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps * batch_size / elapsed


def minigrid_steps_per_s(seconds: float, seed: int = 0) -> float | None:
    """Single-env steps/s of MiniGrid's Fetch-8x8-N3 under random actions; None without minigrid."""
    try:
        import gymnasium
        import minigrid  # noqa: F401  registers the MiniGrid ids
    except ImportError:
        return None
    env = gymnasium.make(MINIGRID_ENV_ID)
    env.reset(seed=seed)
    n_actions = int(env.action_space.n)
    actions = np.random.default_rng(seed).integers(n_actions, size=_ACTION_ROWS).tolist()
    steps, start = 0, time.perf_counter()
    while True:
        for _ in range(_CLOCK_EVERY):
            _, _, terminated, truncated, _ = env.step(actions[steps % _ACTION_ROWS])
            steps += 1
            if terminated or truncated:
                env.reset()
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            env.close()
            return steps / elapsed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="higher-bench world", description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="time per measurement (default: 2)")
    parser.add_argument("--world", default="paper", choices=("paper", "small"))
    parser.add_argument("--no-minigrid", action="store_true", help="skip the MiniGrid reference")
    args = parser.parse_args(argv)

    rates = {b: batched_steps_per_s(args.world, b, args.seconds) for b in BATCH_SIZES}
    reference = None if args.no_minigrid else minigrid_steps_per_s(args.seconds)

    print(f"World steps/s, random actions, {args.seconds:g} s per row (world: {args.world})")
    print(f"{'environment':<34} {'batch':>5} {'steps/s':>12} {'x MiniGrid':>11}")
    print("-" * 65)
    for b, rate in rates.items():
        ratio = f"{rate / reference:.1f}" if reference else "n/a"
        print(f"{'higher_dist BatchedFetchAttr':<34} {b:>5} {rate:>12,.0f} {ratio:>11}")
    if reference is not None:
        print(f"{'minigrid ' + MINIGRID_ENV_ID:<34} {1:>5} {reference:>12,.0f} {'1.0':>11}")
    else:
        print(f"{'minigrid ' + MINIGRID_ENV_ID:<34} {'':>5} {'unavailable':>12}")
    summary = {
        "world": args.world,
        "seconds": args.seconds,
        "b1_steps_per_s": round(rates[1], 1),
        "b64_steps_per_s": round(rates[64], 1),
        "b256_steps_per_s": round(rates[256], 1),
        "minigrid_steps_per_s": None if reference is None else round(reference, 1),
        "ratio_b64": None if not reference else round(rates[64] / reference, 2),
    }
    print(json.dumps(summary))
    return 0
