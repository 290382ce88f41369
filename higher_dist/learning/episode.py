"""The unit of experience that flows actor -> relabeler -> learner: one finished episode.

An episode of T actions keeps T+1 frames: the view before each action plus the view reached by the
last one. The last frame is what a truncated episode bootstraps from.

Achieved outcomes are what hindsight describes. On FetchAttr a pick ends the episode: its one outcome is
that pick (step T-1). On a BabyAI level the agent goes on after reaching an object, opening a door or
picking an object up (the level's kind says which counts), so an episode records each distinct outcome
the level's verifier accepted, in order: the first in `picked` / `pick_step`, up to `MAX_LATER` more in
`later_achieved` / `later_step`. The frame that shows an outcome (`WorldSpec.outcome_view_offset`) is what
the instruction generator describes.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from higher_dist.world.spec import MAX_LATER, OUTCOME_NAMES, SUCCESS, TIMEOUT, WRONG_PICK  # noqa: F401  (world/'s)


def no_later_outcomes() -> tuple[np.ndarray, np.ndarray]:
    """(later_achieved (MAX_LATER, 4) int8, later_step (MAX_LATER,) int32) recording nothing."""
    return np.full((MAX_LATER, 4), -1, np.int8), np.full(MAX_LATER, -1, np.int32)


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
    # Outcomes after the first, in order of their steps, -1 rows and steps past the last; None: none.
    later_achieved: np.ndarray | None = None  # (MAX_LATER, 4) int8, ground truth like `picked`
    later_step: np.ndarray | None = None  # (MAX_LATER,) int32

    def __post_init__(self) -> None:
        if self.pick_step is None:
            self.pick_step = self.length - 1 if self.outcome != TIMEOUT else -1
        self.pick_step = int(self.pick_step)
        if self.later_achieved is None or self.later_step is None:
            self.later_achieved, self.later_step = no_later_outcomes()

    @property
    def n_outcomes(self) -> int:
        """How many achieved outcomes the episode records."""
        return int(self.pick_step >= 0) + int((self.later_step >= 0).sum())

    def outcome_steps(self) -> list[int]:
        """The step of every recorded outcome, in order (what was achieved is not read: a learned
        relabeller may call this)."""
        first = [self.pick_step] if self.pick_step >= 0 else []
        return first + [int(s) for s in self.later_step if s >= 0]

    def outcome_attrs(self, k: int) -> np.ndarray:
        """What outcome number `k` achieved (ground truth, as `picked`)."""
        return self.picked if k == 0 else self.later_achieved[k - 1]

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

    def relabel(self, mission: np.ndarray, reward: float = 1.0, outcome: int = 0) -> "Episode":
        """A copy that claims `mission` was the goal: it ends at achieved outcome number `outcome` (0: the
        first, `pick_step`), which becomes a success with `reward` (the world's reward for a success on that
        step: WorldSpec.pick_reward). The copy is terminal (outcome WRONG_PICK, the achievement ended it);
        steps after it are not in it, and it records that one outcome only."""
        steps = self.outcome_steps()
        if not 0 <= outcome < len(steps):
            raise ValueError(f"Episode.relabel: outcome {outcome} of an episode that records {len(steps)}")
        step = steps[outcome]
        picked = self.picked if outcome == 0 else self.later_achieved[outcome - 1].copy()
        end = step + 1
        rewards = np.zeros(end, dtype=np.float32)
        rewards[-1] = reward
        later_achieved, later_step = no_later_outcomes()
        return replace(self, frames=self.frames[: end + 1], actions=self.actions[:end], rewards=rewards,
                       mission=np.asarray(mission, dtype=np.int64).copy(), outcome=WRONG_PICK,
                       picked=picked, pick_step=step, relabelled=True,
                       later_achieved=later_achieved, later_step=later_step)


@dataclass(frozen=True)
class Withheld:
    """Original episodes the relabeller kept out of the replay (relabel.withheld_while_gated): the learner
    still counts them, so env frames, the replay ratio and the training success stay those of the actors."""

    episodes: int = 0
    frames: int = 0

    def __add__(self, other: "Withheld") -> "Withheld":
        return Withheld(self.episodes + other.episodes, self.frames + other.frames)

    @classmethod
    def of(cls, episodes: list[Episode]) -> "Withheld":
        return cls(len(episodes), sum(ep.length for ep in episodes))


def episodes_state(episodes: list[Episode]) -> dict[str, Any]:
    """Many episodes as one array per field (their arrays end to end, with each one's length beside): a
    checkpoint of thousands of them writes a few tensors, not thousands."""
    state: dict[str, Any] = {"count": len(episodes)}
    for f in fields(Episode):
        values = [getattr(ep, f.name) for ep in episodes]
        if values and isinstance(values[0], np.ndarray):
            state[f.name] = np.concatenate(values)
            state[f.name + "_lengths"] = np.array([len(v) for v in values], np.int64)
        else:
            state[f.name] = np.array(values)
    return state


def episodes_from_state(state: dict[str, Any]) -> list[Episode]:
    columns: dict[str, list] = {}
    for f in fields(Episode):
        if f.name + "_lengths" in state:
            ends = np.cumsum(state[f.name + "_lengths"])[:-1]
            columns[f.name] = np.split(np.asarray(state[f.name]), ends)
        else:  # plain ints and bools again
            columns[f.name] = np.asarray(state[f.name]).tolist()
    return [Episode(**{name: column[i] for name, column in columns.items()}) for i in range(int(state["count"]))]
