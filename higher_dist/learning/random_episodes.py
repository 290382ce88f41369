"""Real episodes for tests, benchmarks and fuzzing: a random policy on the real world.

Anything that checks episodes against the world (the wire's `unpack_episodes`) needs inputs the world
could have produced; hand-made random arrays are not that. These come from the world itself (FetchAttr
or a BabyAI level), with every outcome represented, and optionally the expert's relabelled copies of the
failures that picked something.
"""
from __future__ import annotations

import numpy as np

from higher_dist.config import WorldConfig
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.episode import Episode
from higher_dist.world.spec import SUCCESS, WorldSpec

_KINDS = ("success", "picked", "nothing")  # a success, a failure that picked something, one that did not


def _kind(ep: Episode) -> str:
    return "success" if ep.outcome == SUCCESS else "picked" if ep.pick_step >= 0 else "nothing"


def real_episodes(world: WorldConfig, n: int, seed: int = 0, relabelled: bool = False,
                  n_envs: int = 32, frame_stack: int = 1) -> list[Episode]:
    """`n` episodes of a uniformly random policy, interleaving kinds so that any prefix of three or more
    holds a success, a failure that picked something (FetchAttr: a wrong pick; BabyAI: a time-out after
    a pickup) and one that picked nothing, where the world makes them all (the random policy succeeds a
    few % of the time on the paper world). relabelled: every failure that picked is followed by the
    expert's relabelled copy (counted in `n`)."""
    spec = WorldSpec.of(world)
    collector = EpisodeCollector(world, n_envs, frame_stack, seed)
    rng = np.random.default_rng(seed)
    by_kind: dict[str, list[Episode]] = {k: [] for k in _KINDS}
    for _ in range(200 * spec.max_steps):
        if sum(len(v) for v in by_kind.values()) >= 3 * n and all(by_kind.values()):
            break
        for ep in collector.step(rng.integers(spec.n_actions, size=n_envs)):
            by_kind[_kind(ep)].append(ep)
    out: list[Episode] = []
    turn = 0
    while len(out) < n and any(by_kind.values()):
        pool = by_kind[_KINDS[turn % 3]]
        turn += 1
        if not pool:
            continue
        ep = pool.pop()
        out.append(ep)
        if relabelled and _kind(ep) == "picked" and len(out) < n:
            mission = spec.expert_tokens(ep.picked[None], rng)[0]
            out.append(ep.relabel(mission, float(spec.pick_reward(ep.pick_step + 1))))
    return out
