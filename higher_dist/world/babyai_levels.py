"""Which BabyAI levels are pickup levels, and the facts of a level (view, step limit, locations) that
the world spec needs before any environment runs. Kept apart from the batched adapter (world/babyai.py)
so that world/spec.py can read a level's facts without importing the adapter.
"""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from functools import lru_cache

import gymnasium as gym
import minigrid  # noqa: F401  (registers the BabyAI-* ids with gymnasium)
from minigrid.envs.babyai.core.verifier import PickupInstr

_PROBE_SEED = 0


@contextlib.contextmanager
def _quiet():
    """Minigrid prints every rejected level sample to stdout; in a role's log that is a flood."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def _probe(level_id: str):
    """A fresh unwrapped env of `level_id`, reset once with a fixed seed."""
    env = gym.make(level_id).unwrapped
    with _quiet():
        env.reset(seed=_PROBE_SEED)
    return env


def _only_pickup_missions(env) -> bool:
    """Whether every episode of this level is a lone, non-strict pickup.

    A level generator (LevelGen) draws its instruction kinds per episode, so one seed's mission says
    nothing about the next: require its kinds to be pickup actions only. Strict levels (the *Debug
    variants) end the episode on a wrong pickup, which the episode model above does not have."""
    instrs = getattr(env, "instrs", None)
    if type(instrs) is not PickupInstr or instrs.strict:
        return False
    if hasattr(env, "action_kinds"):
        return set(env.action_kinds) == {"pickup"} and set(env.instr_kinds) == {"action"}
    return True


@lru_cache(maxsize=None)
def pickup_levels() -> tuple[str, ...]:
    """The registered `BabyAI-*` ids whose missions are all non-strict "pick up ..." instructions."""
    levels = []
    for level_id in sorted(k for k in gym.registry if k.startswith("BabyAI-")):
        if _only_pickup_missions(_probe(level_id)):
            levels.append(level_id)
    return tuple(levels)


def is_pickup_level(name: str) -> bool:
    return name in pickup_levels()


@dataclass(frozen=True)
class LevelFacts:
    """What the rest of the system needs to know about a level before running it."""
    level_id: str
    view_size: int
    max_steps: int
    n_actions: int
    has_locations: bool  # missions may name a location ("... on your left"): LevelGen's `locations`
    room_size: int
    grid_width: int
    grid_height: int


@lru_cache(maxsize=None)
def level_facts(level_id: str) -> LevelFacts:
    if not is_pickup_level(level_id):
        known = "known" if level_id in gym.registry else "unknown"
        raise ValueError(f"level {level_id!r} ({known} id) is not a BabyAI pickup level; "
                         f"pickup levels: {', '.join(pickup_levels())}")
    env = _probe(level_id)
    return LevelFacts(level_id=level_id, view_size=int(env.observation_space["image"].shape[0]),
                      max_steps=int(env.max_steps), n_actions=int(env.action_space.n),
                      has_locations=bool(getattr(env, "locations", False)),
                      room_size=int(env.room_size), grid_width=int(env.width), grid_height=int(env.height))
