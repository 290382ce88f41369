"""Samples-per-insert rate limiting, as in Reverb: the replay ratio stays fixed whatever the speed of
the actors. The learner may sample only while it is behind the target ratio, and should stop taking
new experience while it is too far ahead of it (in the cluster that back-pressures the actors through
the sockets' high-water marks)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SamplesPerInsertLimiter:
    samples_per_insert: float
    min_size: int
    tolerance: float = 1024.0  # samples of slack either way before blocking a side

    inserted: int = 0  # inserts counted: env frames of original episodes, or all transitions (replay.ratio_counts)
    sampled: int = 0  # transitions sampled for updates

    def record_insert(self, n: int) -> None:
        self.inserted += n

    def record_sample(self, n: int) -> None:
        self.sampled += n

    def _deficit(self) -> float:
        """How many samples the learner owes the ratio (negative: it is ahead)."""
        return self.samples_per_insert * max(self.inserted - self.min_size, 0) - self.sampled

    def can_sample(self, replay_size: int, batch_size: int) -> bool:
        return replay_size >= self.min_size and self._deficit() >= batch_size - self.tolerance

    def can_insert(self) -> bool:
        """False when the learner is so far behind that more data would lower the replay ratio."""
        return self.inserted < self.min_size or self._deficit() <= self.tolerance

    @property
    def ratio(self) -> float:
        return self.sampled / max(self.inserted, 1)

    def state_dict(self) -> dict:
        return {"inserted": self.inserted, "sampled": self.sampled}

    def load_state_dict(self, state: dict) -> None:
        self.inserted, self.sampled = int(state["inserted"]), int(state["sampled"])
