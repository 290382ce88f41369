"""What a BabyAI level's episode means (the family's part of world/episode_rules.py).

The level itself is minigrid's (world/babyai.py steps it); these rules state what it does, without
importing minigrid, so that a receiver can check episodes of a level:
- reaching, opening or picking the wrong object does not end the episode (the agent goes on); an episode
  ends on the mission's success or at the step limit (a time-out), and a success pays minigrid's reward
  (`WorldSpec.pick_reward`);
- the level's kind says what an achieved outcome is and what shows it in the views: a pickup is a pickup
  action with the object in front before it; an open is a toggle that leaves the door in front open; a
  go-to is any step after which the object is in front (`WorldSpec.outcome_view_offset`).
A described object is (colour, type, location, plural): the location may be unnamed, the plural flag never is.
An achieved object is (colour, type, location mask, plural) (world/babyai_language.py).
"""
from __future__ import annotations

import numpy as np

from higher_dist.world.spec import BABYAI_ACTION_NAMES, BABYAI_DOOR, BABYAI_DOOR_OPEN, SUCCESS, TIMEOUT

# The action that achieves an outcome of each level kind (a go-to: any action).
_ACHIEVE_ACTION = {"pickup": BABYAI_ACTION_NAMES.index("pickup"), "goto": None,
                   "open": BABYAI_ACTION_NAMES.index("toggle")}
# Why an outcome's views do not show it, per kind (one of episode_rules.EPISODE_FAULTS).
_NOT_SHOWN = {"pickup": "picked_not_in_front", "goto": "reached_not_in_front", "open": "door_not_opened"}


class BabyAIEpisodes:

    @staticmethod
    def achieve_action(spec) -> int | None:
        return _ACHIEVE_ACTION[spec.level_kind]

    @staticmethod
    def not_shown_reason(spec) -> str:
        return _NOT_SHOWN[spec.level_kind]

    @staticmethod
    def picks(spec, b) -> np.ndarray:
        """Which episodes achieved something: those with a first outcome's step (the episode may go on)."""
        return (b.pick_step >= 0) & (b.pick_step < b.lengths)

    @staticmethod
    def outcome_attributes_ok(spec, attrs) -> np.ndarray:
        """An achieved outcome's object names colour, type (one this kind's instructions name), plural and
        its location mask (any of 0..15: where the agent started is not in the views, so it is not checked)."""
        types = np.asarray(spec.language.types)
        return (attrs >= 0).all(axis=1) & np.isin(attrs[:, 1], types)

    @classmethod
    def attributes_ok(cls, spec, b, picks) -> np.ndarray:
        """A goal may leave colour, type and location unnamed; its article is always named. A first outcome
        names what `outcome_attributes_ok` says; nothing achieved names nothing."""
        return (b.goal[:, 3] >= 0) & np.where(picks, cls.outcome_attributes_ok(spec, b.picked),
                                              (b.picked == -1).all(axis=1))

    @staticmethod
    def cells_ok(spec, frames) -> None:
        """Any cell of minigrid's tables may show (the spec's value ranges are the whole rule)."""
        return None

    @staticmethod
    def shown(spec, b, step, attrs) -> np.ndarray:
        """Per episode, whether its views show outcome `attrs (N, 4)` achieved on its step `step (N,)`."""
        if spec.level_kind == "open":  # a door of that colour in front, open after the toggle
            before, after = spec.front_cell(b.frame_at(step)), spec.front_cell(b.frame_after(step))
            return ((before[:, 0] == BABYAI_DOOR) & (before[:, 1] == attrs[:, 0]) & (after[:, 0] == BABYAI_DOOR)
                    & (after[:, 1] == attrs[:, 0]) & (after[:, 2] == BABYAI_DOOR_OPEN))
        frame = b.frame_after(step) if spec.outcome_view_offset else b.frame_at(step)
        return (spec.front_object(frame)[:, :2] == attrs[:, :2]).all(axis=1)

    @classmethod
    def outcome_ok(cls, spec, b, last_action) -> np.ndarray:
        """An original ends in a success (its last step the kind's achieving action) or at the step limit.
        A relabelled copy ends at its own outcome instead; episode_rules checks that rule for every family."""
        action = cls.achieve_action(spec)
        success_ok = (b.outcome == SUCCESS) & ((last_action == action) if action is not None else True)
        ok = np.where(b.outcome == TIMEOUT, b.lengths == spec.max_steps, success_ok)
        return ok | b.relabelled

    @staticmethod
    def reward(spec, b) -> np.ndarray:
        """The last step's reward of an original episode: a success's (minigrid's, `spec.pick_reward`),
        else nothing (a wrong object pays 0)."""
        return np.where(b.outcome == SUCCESS, spec.pick_reward(b.lengths), 0.0)

    @staticmethod
    def mission_ok(spec, named) -> bool:
        """Every sentence the level's grammar parses names an object a level may hold."""
        return True


BABYAI_EPISODES = BabyAIEpisodes()
