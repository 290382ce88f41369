"""Which BabyAI levels are supported (every episode one non-strict pickup, go-to or open instruction: the
level's `kind`), and the facts of a level (kind, view, step limit, locations) that the world spec needs
before any environment runs. Kept apart from the batched adapter (world/babyai.py)
so that world/spec.py can read a level's facts without importing the adapter.
"""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from functools import lru_cache

import gymnasium as gym
import minigrid  # noqa: F401  (registers the BabyAI-* ids with gymnasium)
from minigrid.envs.babyai.core.verifier import GoToInstr, OpenInstr, PickupInstr

_PROBE_SEED = 0
# A level that is not a level generator draws its instruction in code; more seeds confirm that every
# episode has the first one's kind (BabyAI-ActionObjDoor-v0 mixes go-to, pickup and open missions).
_CONFIRM_SEEDS = range(1, 25)
_KIND_OF_INSTR = {PickupInstr: "pickup", GoToInstr: "goto", OpenInstr: "open"}
SUPPORTED = "levels whose every mission is one non-strict 'pick up', 'go to' or 'open' instruction"


@contextlib.contextmanager
def _quiet():
    """Minigrid prints every rejected level sample to stdout; in a role's log that is a flood."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def _probe(level_id: str, seed: int = _PROBE_SEED):
    """A fresh unwrapped env of `level_id`, reset once with `seed`."""
    env = gym.make(level_id).unwrapped
    with _quiet():
        env.reset(seed=seed)
    return env


def _instr_kind(env) -> str | None:
    """The kind of the env's current instruction: one non-strict pickup, go-to or open, else None
    (sequences, PutNext, strict variants that end an episode on a wrong object)."""
    instrs = getattr(env, "instrs", None)
    kind = _KIND_OF_INSTR.get(type(instrs))
    return None if kind is None or getattr(instrs, "strict", False) else kind


@lru_cache(maxsize=None)
def _level_kind(level_id: str) -> str | None:
    """The one kind of every episode of the level, None if its episodes are not all of one supported kind.

    A level generator (LevelGen) draws its instruction kinds per episode, so one seed's mission says
    nothing about the next: require its kinds to be one action only. Other levels are probed on more seeds."""
    env = _probe(level_id)
    kind = _instr_kind(env)
    if kind is None:
        return None
    if hasattr(env, "action_kinds"):
        ok = set(env.action_kinds) == {kind} and set(env.instr_kinds) == {"action"}
        return kind if ok else None
    with _quiet():
        for seed in _CONFIRM_SEEDS:
            env.reset(seed=seed)
            if _instr_kind(env) != kind:
                return None
    return kind


@lru_cache(maxsize=None)
def _kinds() -> dict[str, str]:
    kinds = {}
    for level_id in sorted(k for k in gym.registry if k.startswith("BabyAI-")):
        kind = level_kind(level_id)
        if kind is not None:
            kinds[level_id] = kind
    return kinds


def supported_levels(kind: str | None = None) -> tuple[str, ...]:
    """The registered `BabyAI-*` ids this system runs (of one `kind` if given), sorted."""
    return tuple(level for level, k in _kinds().items() if kind is None or k == kind)


def pickup_levels() -> tuple[str, ...]:
    """The supported levels whose missions are all "pick up ..." instructions."""
    return supported_levels("pickup")


def level_kind(name: str) -> str | None:
    """"pickup", "goto" or "open" for a supported level id, None for any other name."""
    return _level_kind(name) if isinstance(name, str) and name.startswith("BabyAI-") and name in gym.registry else None


def is_supported_level(name: str) -> bool:
    return level_kind(name) is not None


def is_pickup_level(name: str) -> bool:
    return level_kind(name) == "pickup"


def _names_locations(env) -> bool:
    """Whether the level's missions may name a location: a level generator says so (`locations`); other
    levels are probed on the confirming seeds (BabyAI-OpenDoor-v0 names one in about half its missions)."""
    if hasattr(env, "locations"):
        return bool(env.locations)
    with _quiet():
        for seed in (_PROBE_SEED, *_CONFIRM_SEEDS):
            env.reset(seed=seed)
            if getattr(env.instrs.desc, "loc", None) is not None:
                return True
    return False


@dataclass(frozen=True)
class LevelFacts:
    """What the rest of the system needs to know about a level before running it."""
    level_id: str
    kind: str  # "pickup", "goto" or "open": the verb of every mission of the level
    view_size: int
    max_steps: int
    n_actions: int
    has_locations: bool  # missions may name a location ("... on your left")
    room_size: int
    grid_width: int
    grid_height: int


@lru_cache(maxsize=None)
def level_facts(level_id: str) -> LevelFacts:
    if not is_supported_level(level_id):
        known = "known" if level_id in gym.registry else "unknown"
        raise ValueError(f"level {level_id!r} ({known} id) is not supported: supported are {SUPPORTED} "
                         f"({', '.join(supported_levels())})")
    env = _probe(level_id)
    return LevelFacts(level_id=level_id, kind=level_kind(level_id), view_size=int(env.observation_space["image"].shape[0]),
                      max_steps=int(env.max_steps), n_actions=int(env.action_space.n),
                      has_locations=_names_locations(env),
                      room_size=int(env.room_size), grid_width=int(env.width), grid_height=int(env.height))
