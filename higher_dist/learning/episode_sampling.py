"""Whole episodes drawn from the prioritized replay, for the recurrent core (learning/recurrent.py).

An episode is drawn with probability proportional to the summed priorities of its transitions: a draw
picks a transition as `PrioritizedReplay.sample` does and takes the episode that holds it. With every
priority equal that is proportional to the episode's length, which is what uniform transitions give;
the importance weight of an episode, (length / mass)^beta normalised by the batch's largest, undoes the
priorities' bias relative to that. The TD errors come back per transition and go to the transitions'
own priorities, so a surprising step makes its whole episode likelier to be replayed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["EpisodeSampling", "SequenceBatch"]


@dataclass
class SequenceBatch:
    """B episodes padded to the longest one's T steps (`mask` marks the real ones)."""

    indices: np.ndarray  # (B, T) int64 slots of the transitions, for update_priorities (0 on padding)
    generations: np.ndarray  # (B, T) int64 write serials of those slots
    frames: np.ndarray  # (B, T+1, V, V, 4) uint8, frame 0 first; padded with the episode's final frame
    mission: np.ndarray  # (B, L) int64
    action: np.ndarray  # (B, T) int64
    reward: np.ndarray  # (B, T) float32 n-step discounted return
    discount: np.ndarray  # (B, T) float32 gamma^m, or 0 when the n steps reach a terminal pick
    next_step: np.ndarray  # (B, T) int64 t + m: the step the target bootstraps from
    mask: np.ndarray  # (B, T) float32, 1 on real steps
    weights: np.ndarray  # (B,) float32 importance weights of the episodes, max 1

    @property
    def valid(self) -> np.ndarray:
        """(B, T) bool: the real transitions (what update_priorities takes)."""
        return self.mask > 0

    @property
    def transitions(self) -> int:
        return int(self.mask.sum())

    def priority_update(self, priorities: np.ndarray) -> tuple:
        """(slots, priorities, generations) for `update_priorities`: the real steps of (B, T) priorities."""
        valid = self.valid
        return self.indices[valid], priorities[valid], self.generations[valid]

    def __len__(self) -> int:
        return self.transitions


class EpisodeSampling:
    """`sample_episodes` for PrioritizedReplay (a mixin: it reads the replay's slot arrays and tree)."""

    def sample_episodes(self, n_episodes: int, beta: float, rng: np.random.Generator | None = None) -> SequenceBatch:
        """A prioritized batch of `n_episodes` whole episodes (one may come twice, as a transition may
        in `sample`); `rng` defaults to the replay's own generator."""
        if self._size == 0:
            raise ValueError("the replay holds no transitions to sample")
        if n_episodes < 1:
            raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
        rng = self._rng if rng is None else rng
        tree, c = self._tree, self.capacity
        records = self._episode[tree.sample_stratified(n_episodes, rng)]
        steps = self._ep_slots[records].astype(np.int64) - 1  # transitions; the last slot is the final frame
        longest = int(steps.max())
        t = np.arange(longest + 1)
        # Frame slots of each episode from its start, the final frame repeated past the end.
        offsets = np.minimum(t[None, :], steps[:, None])
        slots = (self._ep_start[records][:, None] + offsets) % c  # (B, T+1)
        mask = t[None, :longest] < steps[:, None]
        step_slots = slots[:, :longest]
        priority = np.where(mask, tree.get(step_slots), 0.0)
        # Episode i's draw probability is mass_i / total; uniform transitions would give steps_i / N.
        ratio = steps / priority.sum(axis=1)
        weights = np.power(ratio / ratio.max(), beta)
        next_step = np.where(mask, t[None, :longest] + self._next_offset[step_slots], t[None, :longest])
        return SequenceBatch(
            indices=np.where(mask, step_slots, 0),
            generations=self._generation[step_slots],
            frames=self._frames[slots],
            mission=self._ep_mission[records].astype(np.int64),
            action=np.where(mask, self._action[step_slots], 0).astype(np.int64),
            reward=np.where(mask, self._return[step_slots], 0.0).astype(np.float32),
            discount=np.where(mask, self._discount[step_slots], 0.0).astype(np.float32),
            next_step=next_step.astype(np.int64),
            mask=mask.astype(np.float32),
            weights=weights.astype(np.float32),
        )
