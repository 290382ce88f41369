"""Structure-aware hostile episodes: messages that pass the codec's schema but are wrong for the run.

Each mutation takes real episodes (learning/random_episodes.py) and breaks one thing a peer could lie about;
`hostile_message` returns the encoded frames together with what the receiver must do with them (how
many episodes it must drop, under which reason). The fuzz tests drive real learners and relabelers with
these. Used only to attack this project's own processes.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from higher_dist.learning.episode import Episode
from higher_dist.wire import codec
from higher_dist.wire.episodes import pack_episodes
from higher_dist.world.language import PAD, expert_tokens, parse
from higher_dist.world.spec import ACTION_FORWARD, SUCCESS, TIMEOUT, WRONG_PICK, WorldSpec


@dataclass
class Hostile:
    kind: str
    frames: list  # encoded message
    rejects: int  # episodes (or whole messages) the receiver must drop and count
    reason: str  # the reason it must count them under
    sender: str


@dataclass
class Pools:
    """Real episodes by outcome, to mutate."""

    success: list[Episode]
    wrong_pick: list[Episode]
    timeout: list[Episode]

    @classmethod
    def of(cls, episodes: list[Episode]) -> "Pools":
        originals = [ep for ep in episodes if not ep.relabelled]
        return cls([e for e in originals if e.outcome == SUCCESS], [e for e in originals if e.outcome == WRONG_PICK],
                   [e for e in originals if e.outcome == TIMEOUT])

    def pick(self, rng: np.random.Generator, outcome: str, max_length: int | None = None) -> Episode:
        pool = [ep for ep in getattr(self, outcome) if max_length is None or ep.length <= max_length]
        ep = pool[int(rng.integers(len(pool)))]
        return replace(ep, frames=ep.frames.copy(), actions=ep.actions.copy(), rewards=ep.rewards.copy(),
                       mission=ep.mission.copy(), picked=ep.picked.copy(), goal=ep.goal.copy())


Mutation = Callable[[Pools, np.random.Generator, WorldSpec], "tuple[list[Episode] | dict, str]"]


def _other_object(ep: Episode, spec: WorldSpec, rng: np.random.Generator, avoid=()) -> np.ndarray:
    while True:
        obj = np.array([rng.choice(v) for v in spec.world_values], dtype=np.int8)
        if not (obj == ep.goal).all() and not any((obj == a).all() for a in avoid):
            return obj


def m_mission_token(p, rng, spec):
    ep = p.pick(rng, "wrong_pick")
    ep.mission[int(rng.integers(spec.mission_len))] = int(rng.integers(spec.vocab_size, 1024))
    return [ep], "mission_token"


def m_all_pad(p, rng, spec):
    ep = p.pick(rng, "success")
    ep.mission[:] = PAD
    return [ep], "mission_grammar"


def m_ungrammatical(p, rng, spec):
    ep = p.pick(rng, "timeout")
    words = ep.mission[ep.mission != PAD]
    shuffled = words[::-1].copy()  # the type word first: never a sentence of the grammar
    ep.mission[: len(words)] = shuffled
    assert parse(ep.mission) is None
    return [ep], "mission_grammar"


def m_wrong_goal(p, rng, spec):
    ep = p.pick(rng, "timeout")
    ep.mission = expert_tokens(_other_object(ep, spec, rng)[None], rng)[0]
    return [ep], "mission_goal"


def m_goal_none(p, rng, spec):
    ep = p.pick(rng, "timeout")
    ep.goal[int(rng.integers(4))] = -1
    return [ep], "attribute"


def m_picked_none(p, rng, spec):
    ep = p.pick(rng, "wrong_pick")
    ep.picked[:] = -1
    return [ep], "attribute"


def m_impossible_cell(p, rng, spec):
    ep = p.pick(rng, "timeout")
    t, r, c = int(rng.integers(len(ep.frames))), int(rng.integers(spec.view_size)), int(rng.integers(spec.view_size))
    cell = ep.frames[t, r, c]
    if cell[0] >= 3:  # an object without its colour
        cell[1] = 0
    else:  # a wall or an empty cell with a colour
        cell[0], cell[1] = 2, 1 + int(rng.choice(spec.world_values[0]))
    return [ep], "cell"


def m_outcome_flip(p, rng, spec):
    ep = p.pick(rng, "success")
    ep.outcome = WRONG_PICK
    return [ep], "outcome"


def m_short_timeout(p, rng, spec):
    ep = p.pick(rng, "wrong_pick", max_length=spec.max_steps - 1)
    ep.outcome, ep.picked[:] = TIMEOUT, -1
    return [ep], "outcome"


def m_success_without_pick(p, rng, spec):
    ep = p.pick(rng, "success")
    ep.actions[-1] = ACTION_FORWARD
    return [ep], "outcome"


def m_reward_on_wrong_pick(p, rng, spec):
    ep = p.pick(rng, "wrong_pick")
    ep.rewards[-1] = 1.0
    return [ep], "reward"


def m_reward_midway(p, rng, spec):
    ep = p.pick(rng, "timeout")
    ep.rewards[int(rng.integers(len(ep.rewards) - 1))] = float(rng.choice([0.25, 0.5, 1.0]))
    return [ep], "reward"


def m_picked_elsewhere(p, rng, spec):
    ep = p.pick(rng, "wrong_pick")
    ep.picked = _other_object(ep, spec, rng, avoid=[ep.picked])
    return [ep], "picked_not_in_front"


def m_relabelled_success(p, rng, spec):
    ep = p.pick(rng, "success")
    ep.relabelled = True
    return [ep], "relabel_inconsistent"


def m_contradicting_relabel(p, rng, spec):
    ep = p.pick(rng, "wrong_pick")
    return [ep.relabel(ep.mission)], "relabel_inconsistent"  # "reached" the goal it just failed


def m_actor_id(p, rng, spec):
    ep = p.pick(rng, "timeout")
    ep.actor_id = int(rng.integers(1000, 1 << 20))
    return [ep], "actor_id"


def m_too_long(p, rng, spec):
    ep = p.pick(rng, "timeout")
    ep.frames = np.concatenate([ep.frames, ep.frames[-1:]])
    ep.actions = np.append(ep.actions, np.uint8(ACTION_FORWARD))
    ep.rewards = np.append(ep.rewards, np.float32(0))
    return [ep], "episode_length"


def m_huge_batch(p, rng, spec):
    """Thousands of episodes in one message, every one with an all-PAD mission: near the schema's limits."""
    ep = p.pick(rng, "timeout")
    ep.mission[:] = PAD
    return [ep] * int(rng.integers(2000, 4000)), "mission_grammar"


# Whole-message faults: the batch's structure is wrong for this run's world (one reject per message).
def m_mission_len(p, rng, spec):
    fields, arrays = pack_episodes([p.pick(rng, "success")])
    arrays["mission"] = np.concatenate([arrays["mission"], np.zeros((1, 1), np.int64)], axis=1)
    return (fields, arrays), "shape"


def m_view_size(p, rng, spec):
    ep = p.pick(rng, "timeout")
    fields, arrays = pack_episodes([ep])
    arrays["frames"] = np.pad(arrays["frames"], ((0, 0), (1, 1), (1, 1), (0, 0)))
    return (fields, arrays), "shape"


def m_lengths_sum(p, rng, spec):
    fields, arrays = pack_episodes([p.pick(rng, "timeout"), p.pick(rng, "wrong_pick")])
    arrays["lengths"] = arrays["lengths"] + np.array([1, 0], np.int32)  # one step more than carried
    return (fields, arrays), "shape"


MUTATIONS: dict[str, Mutation] = {
    name[2:]: fn for name, fn in globals().items() if name.startswith("m_") and callable(fn)
}
# Reasons that depend on who receives the message (the relabeler takes no relabelled copies at all).
ORIGIN_SENSITIVE = {"relabelled_success", "contradicting_relabel"}


def hostile_message(kind: str, pools: Pools, rng: np.random.Generator, spec: WorldSpec, sender: str,
                    to_relabeler: bool) -> Hostile:
    built, reason = MUTATIONS[kind](pools, rng, spec)
    if isinstance(built, tuple):
        fields, arrays = built
        rejects = 1
    else:
        fields, arrays = pack_episodes(built)
        rejects = len(built)
        if kind in ORIGIN_SENSITIVE and (to_relabeler or sender != "relabeler"):
            reason = "relabel_origin"
    return Hostile(kind, codec.encode("episodes", fields, arrays, sender=sender), rejects, reason, sender)
