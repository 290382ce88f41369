"""Lies a peer could tell about a BabyAI level's episodes, each made from a real episode: what the
receiver must drop, and under which reason (higher_dist/wire/episodes.py). Used by the unit test of the
boundary and by the fuzz test of real learner and relabeler processes on a level."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from higher_dist.learning.episode import SUCCESS, TIMEOUT, Episode
from higher_dist.learning.hindsight.relabel import ExpertRelabel
from higher_dist.world import babyai_language as lang
from higher_dist.world.spec import WorldSpec

# Lies about an original episode (any sender), and about a relabelled copy (only the relabeler may send one).
ORIGINAL_LIES = ("short_timeout", "success_reward", "pick_not_a_pickup", "picked_elsewhere", "mission_not_the_goal",
                 "ungrammatical", "padding_channel", "plural_unset")
COPY_LIES = ("copy_goes_on", "copy_unrewarded")
LIES = ORIGINAL_LIES + COPY_LIES


def lie(kind: str, episodes: list[Episode], spec: WorldSpec, rng: np.random.Generator) -> tuple[Episode, str]:
    """One episode of `episodes` (real ones of the level) made wrong in one way, and the reason the
    receiver must drop it under."""
    successes = [ep for ep in episodes if ep.outcome == SUCCESS and not ep.relabelled]
    failures = [ep for ep in episodes if ep.outcome == TIMEOUT and ep.pick_step >= 0]
    success = successes[int(rng.integers(len(successes)))]
    failed = failures[int(rng.integers(len(failures)))]
    copy = ExpertRelabel(spec=spec).relabel([failed])[0]

    def clone(ep: Episode, **changes) -> Episode:
        fresh = dict(frames=ep.frames.copy(), actions=ep.actions.copy(), rewards=ep.rewards.copy(),
                     mission=ep.mission.copy())
        return replace(ep, **{**fresh, **changes})

    if kind == "short_timeout":
        return clone(failed, frames=failed.frames[:-1], actions=failed.actions[:-1], rewards=failed.rewards[:-1]), "outcome"
    if kind == "success_reward":
        ep = clone(success)
        ep.rewards[-1] = 1.0
        return ep, "reward"
    if kind == "pick_not_a_pickup":
        ep = clone(failed)
        ep.actions[ep.pick_step] = 2
        return ep, "outcome"
    if kind == "picked_elsewhere":
        ep = clone(failed, picked=failed.picked.copy())
        ep.picked[0] = (ep.picked[0] + 1) % len(lang.COLORS)
        return ep, "picked_not_in_front"
    if kind == "copy_goes_on":  # a copy that keeps the steps after its pick, rewarded at the end
        ep = clone(failed, relabelled=True, mission=copy.mission)
        ep.rewards[-1] = spec.pick_reward(ep.length)
        return ep, "relabel_inconsistent"
    if kind == "copy_unrewarded":
        ep = clone(copy)
        ep.rewards[-1] = 0.0
        return ep, "reward"
    if kind == "mission_not_the_goal":
        other = lang.mission_tokens(np.array([[(success.goal[0] + 1) % 6, success.goal[1], -1, 0]]))[0]
        return clone(success, mission=other), "mission_goal"
    if kind == "ungrammatical":
        ep = clone(success)
        ep.mission[:3] = ep.mission[[1, 0, 2]]  # "up pick ..."
        return ep, "mission_grammar"
    if kind == "padding_channel":
        ep = clone(success)
        ep.frames[0, 0, 0, 3] = 1  # the fourth channel of a BabyAI view is always 0
        return ep, "cell"
    if kind == "plural_unset":
        return clone(success, goal=np.array([*success.goal[:3], -1], np.int8)), "attribute"
    raise KeyError(kind)
