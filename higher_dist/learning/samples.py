"""Real episodes for tests, benchmarks and fuzzing: a random policy on the real world.

Anything that checks episodes against the world (the wire's `unpack_episodes`) needs inputs the world
could have produced; hand-made random arrays are not that. These come from `BatchedFetchAttr` itself,
with every outcome represented, and optionally the expert's relabelled copies of the wrong picks.
"""
from __future__ import annotations

import numpy as np

from higher_dist.config import WorldConfig
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.episode import Episode
from higher_dist.world.language import expert_tokens
from higher_dist.world.spec import N_ACTIONS, SUCCESS, TIMEOUT, WRONG_PICK


def real_episodes(world: WorldConfig, n: int, seed: int = 0, relabelled: bool = False,
                  n_envs: int = 32, frame_stack: int = 1) -> list[Episode]:
    """`n` episodes of a uniformly random policy, interleaving outcomes so that any prefix of three or
    more holds a success, a wrong pick and a time-out where the world makes them all (the random policy
    succeeds a few % of the time on the paper world). relabelled: every wrong pick is followed by the
    expert's relabelled copy (counted in `n`)."""
    collector = EpisodeCollector(world, n_envs, frame_stack, seed)
    rng = np.random.default_rng(seed)
    by_outcome: dict[int, list[Episode]] = {SUCCESS: [], WRONG_PICK: [], TIMEOUT: []}
    for _ in range(200 * world.max_steps):
        if sum(len(v) for v in by_outcome.values()) >= 3 * n and all(by_outcome.values()):
            break
        for ep in collector.step(rng.integers(N_ACTIONS, size=n_envs)):
            by_outcome[ep.outcome].append(ep)
    out: list[Episode] = []
    turn = 0
    while len(out) < n and any(by_outcome.values()):
        pool = by_outcome[(SUCCESS, WRONG_PICK, TIMEOUT)[turn % 3]]
        turn += 1
        if not pool:
            continue
        ep = pool.pop()
        out.append(ep)
        if relabelled and ep.outcome == WRONG_PICK and len(out) < n:
            out.append(ep.relabel(expert_tokens(ep.picked[None], rng)[0]))
    return out
