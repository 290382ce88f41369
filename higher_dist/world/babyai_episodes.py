"""What a BabyAI pickup level's episode means (the family's part of world/episode_rules.py).

The level itself is minigrid's (world/babyai.py steps it); these rules state what it does, without
importing minigrid, so that a receiver can check episodes of a level: a wrong pickup does not end the
episode (the agent carries on), an episode ends on the mission's pickup (a success) or at the step limit
(a time-out), and a success pays minigrid's reward (`WorldSpec.pick_reward`). A described object is (colour,
type, location, plural): the location may be unnamed, the plural flag never is.
"""
from __future__ import annotations

import numpy as np

from higher_dist.world.spec import BABYAI_ACTION_NAMES, SUCCESS, TIMEOUT


class BabyAIEpisodes:
    pick_action = BABYAI_ACTION_NAMES.index("pickup")

    @staticmethod
    def picks(spec, b) -> np.ndarray:
        """Which episodes picked up an object: those with a pick step (the first pickup, the one hindsight
        describes; the episode may go on after it)."""
        return (b.pick_step >= 0) & (b.pick_step < b.lengths)

    @staticmethod
    def attributes_ok(spec, b, picks) -> np.ndarray:
        """A goal may leave colour, type and location unnamed; its article is always named. A picked object
        names colour, type and plural, never a location; nothing picked names nothing."""
        picked_set = (b.picked[:, [0, 1, 3]] >= 0).all(axis=1) & (b.picked[:, 2] == -1)
        return (b.goal[:, 3] >= 0) & np.where(picks, picked_set, (b.picked == -1).all(axis=1))

    @staticmethod
    def cells_ok(spec, frames) -> None:
        """Any cell of minigrid's tables may show (the spec's value ranges are the whole rule)."""
        return None

    @classmethod
    def outcome_ok(cls, spec, b, last_action) -> np.ndarray:
        """An original ends in a success (its last step a pickup) or at the step limit. A relabelled copy
        ends at its own pick instead; episode_rules checks that rule for every family."""
        ok = np.where(b.outcome == TIMEOUT, b.lengths == spec.max_steps,
                      (b.outcome == SUCCESS) & (last_action == cls.pick_action))
        return ok | b.relabelled

    @staticmethod
    def reward(spec, b) -> np.ndarray:
        """The last step's reward of an original episode: a success's (minigrid's, `spec.pick_reward`),
        else nothing (a wrong pickup pays 0)."""
        return np.where(b.outcome == SUCCESS, spec.pick_reward(b.lengths), 0.0)

    @staticmethod
    def mission_ok(spec, named) -> bool:
        """Every sentence the level's grammar parses names an object a level may hold."""
        return True


BABYAI_EPISODES = BabyAIEpisodes()
