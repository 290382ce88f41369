"""The one place that turns a world config into a batched world: FetchAttr or a BabyAI level.

Both give the same interface: `reset() -> (views (B, V, V, 4) uint8, missions (B, L) int64)` and
`step(actions) -> StepResult`, with finished episodes restarting in place.
"""
from __future__ import annotations

from higher_dist.config import WorldConfig, is_babyai_world
from higher_dist.world.grid import BatchedFetchAttr


def batched_world(world: WorldConfig, n_envs: int, seed: int = 0, goal_set: str = "train", env_seeds=None):
    """`n_envs` environments of `world`, env i seeded from [seed, i], or from `env_seeds[i]` when given
    (one seed per env). `goal_set` (train | heldout) chooses FetchAttr's goals; a BabyAI level has only
    its own missions (train)."""
    if is_babyai_world(world.name):
        if goal_set != "train":
            raise ValueError(f"goal_set: BabyAI levels have no held-out goals, got {goal_set!r}")
        from higher_dist.world.babyai import BatchedBabyAI  # imports minigrid: only for BabyAI runs
        return BatchedBabyAI(world.name, n_envs, seed, env_seeds=env_seeds, max_steps=world.max_steps or None)
    return BatchedFetchAttr(world, n_envs, seed, goal_set=goal_set, env_seeds=env_seeds)
