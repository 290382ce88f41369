"""The unit of experience that flows actor -> relabeler -> learner: one finished episode.

An episode of T actions keeps T+1 frames: the view before each action plus the view reached by the
last one. The last frame is what a truncated episode bootstraps from. `pick_step` is the step whose
action picked the object hindsight describes: on FetchAttr a pick ends the episode (T-1); on a BabyAI
level the agent may pick, carry and drop, and it is the episode's first pick. The frame before that
pick (`frames[pick_step]`) is what the instruction generator describes.
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
    # Step of the pick that `picked` describes, -1 if nothing was picked. None: the FetchAttr rule, a pick
    # ends the episode (the last step for SUCCESS and WRONG_PICK, none for a TIMEOUT).
    pick_step: int | None = None
    relabelled: bool = False
    actor_id: int = 0
    weights_version: int = 0

    def __post_init__(self) -> None:
        if self.pick_step is None:
            self.pick_step = self.length - 1 if self.outcome != TIMEOUT else -1
        self.pick_step = int(self.pick_step)

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

    def relabel(self, mission: np.ndarray, reward: float = 1.0) -> "Episode":
        """A copy that claims `mission` was the goal: it ends at the pick (`pick_step`), which becomes a
        success with `reward` (the world's reward for a success on that step: WorldSpec.pick_reward).
        The copy is terminal (outcome WRONG_PICK, the pick ended it); steps after the pick are not in it."""
        if self.pick_step < 0:
            raise ValueError("Episode.relabel: nothing was picked, there is nothing to describe")
        end = self.pick_step + 1
        rewards = np.zeros(end, dtype=np.float32)
        rewards[-1] = reward
        return replace(self, frames=self.frames[: end + 1], actions=self.actions[:end], rewards=rewards,
                       mission=np.asarray(mission, dtype=np.int64).copy(), outcome=WRONG_PICK,
                       relabelled=True)
