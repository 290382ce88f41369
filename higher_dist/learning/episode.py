"""The unit of experience that flows actor -> relabeler -> learner: one finished episode.

An episode of T actions keeps T+1 frames: the view before each action plus the view reached by the
last one. The last frame is what a truncated episode bootstraps from; the frame before the final pick
(`frames[T-1]`) is what the instruction generator describes.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from higher_dist.world.spec import OUTCOME_NAMES, SUCCESS, TIMEOUT, WRONG_PICK  # noqa: F401  (owned by world/)


@dataclass
class Episode:
    frames: np.ndarray  # (T+1, V, V, 4) uint8
    actions: np.ndarray  # (T,) uint8
    rewards: np.ndarray  # (T,) float32; a pick's reward sits on the last step
    mission: np.ndarray  # (MISSION_LEN,) int64 word ids, PAD-padded (the instruction the agent followed)
    outcome: int  # SUCCESS, WRONG_PICK or TIMEOUT
    picked: np.ndarray  # (4,) int8 attributes of the picked object, -1 if none. Ground truth: metrics and
    #                     the expert only; a learned relabeller must never read it.
    goal: np.ndarray  # (4,) int8 goal attributes (ground truth as well)
    relabelled: bool = False
    actor_id: int = 0
    weights_version: int = 0

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])

    @property
    def terminated(self) -> bool:
        """A pick ended it: no bootstrap past the last step. A time-out is a truncation instead."""
        return self.outcome != TIMEOUT

    @property
    def origin(self) -> str:
        return "relabelled" if self.relabelled else OUTCOME_NAMES[self.outcome]

    def relabel(self, mission: np.ndarray) -> "Episode":
        """A copy that claims `mission` was the goal: the final pick becomes a success (reward 1)."""
        rewards = self.rewards.copy()
        rewards[-1] = 1.0
        return replace(self, mission=np.asarray(mission, dtype=np.int64).copy(), rewards=rewards,
                       relabelled=True)
