"""Every random stream of a run, derived from one `numpy.random.SeedSequence`.

The run's sequence has the entropy (PROJECT_ENTROPY, cfg.seed); each stream is its child with the
spawn key (role, index, purpose): the actor's number for an actor, the frame count for an evaluation,
0 for the learner and the relabeler. A stream is handed out as 63-bit integers (they fit a torch seed,
an int64 and msgpack), so two streams of one run, or of two runs, coincide only if SeedSequence's
hash collides. In particular two run seeds never evaluate on the same episodes, whereas the same run
seed and frame count always evaluate on the same ones.

This module is the one place that knows how a seed is made; every component takes the integer it is
handed (DQNUpdater's `seed`, a world's `env_seeds`, ...).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

# "higher-d" in ASCII. Mixed into every run's entropy so that a run's streams never equal a generator
# seeded elsewhere with a bare small int (default_rng(0), a world's `seed=0`, a test's seed).
PROJECT_ENTROPY = 0x6869676865722D64


class Role(IntEnum):
    LEARNER = 1
    RELABELER = 2
    ACTOR = 3
    EVALUATION = 4


class Purpose(IntEnum):
    TORCH = 1  # a process's global torch RNG
    NETWORK_INIT = 2  # the learner's Q-network initialisation
    REPLAY = 3  # the learner's replay sampling
    GENERATOR_INIT = 4  # the relabeler's instruction generator initialisation
    DATASET_SPLIT = 5  # the generator dataset's train / validation split
    GENERATOR_BATCHES = 6  # the generator's training minibatches
    RELABEL_DRAWS = 7  # expert wording, noisy expert's swapped attributes
    ENVS = 8  # one seed per environment of an actor
    EXPLORATION = 9  # an actor's epsilon-greedy and action-repeat draws
    EPISODES = 10  # one seed per environment (episode) of an evaluation


@dataclass(frozen=True)
class RelabelerSeeds:
    """The relabeler's streams, as the relabel strategies and the generator's trainer take them."""

    draws: int
    generator_init: int
    dataset_split: int
    generator_batches: int

    @staticmethod
    def of(seed: int | RelabelerSeeds) -> RelabelerSeeds:
        """`seed` as is, or, for an int, the relabeler's streams of a run with that seed."""
        return seed if isinstance(seed, RelabelerSeeds) else Seeds(seed).relabeler


@dataclass(frozen=True)
class Seeds:
    """Every seed of a run, from its `cfg.seed`."""

    run_seed: int

    def __post_init__(self):
        if isinstance(self.run_seed, bool) or not isinstance(self.run_seed, (int, np.integer)) or self.run_seed < 0:
            raise ValueError(f"seed: must be a non-negative integer, got {self.run_seed!r}")

    # -- the derivation ------------------------------------------------------------------------------
    def stream(self, role: Role, index: int, purpose: Purpose) -> np.random.SeedSequence:
        if index < 0:
            raise ValueError(f"seed stream index: must be >= 0, got {index}")
        return np.random.SeedSequence((PROJECT_ENTROPY, int(self.run_seed)),
                                      spawn_key=(int(role), int(index), int(purpose)))

    def integers(self, role: Role, index: int, purpose: Purpose, n: int) -> list[int]:
        """The first `n` 63-bit integers of a stream (a prefix: n + 1 starts with the same n)."""
        words = self.stream(role, index, purpose).generate_state(n, np.uint64) >> np.uint64(1)
        return [int(w) for w in words]

    def integer(self, role: Role, index: int, purpose: Purpose) -> int:
        return self.integers(role, index, purpose, 1)[0]

    # -- the learner ---------------------------------------------------------------------------------
    @property
    def learner_torch(self) -> int:  # the learner's (or single-process runner's) global torch RNG
        return self.integer(Role.LEARNER, 0, Purpose.TORCH)

    @property
    def learner_init(self) -> int:
        return self.integer(Role.LEARNER, 0, Purpose.NETWORK_INIT)

    @property
    def learner_replay(self) -> int:
        return self.integer(Role.LEARNER, 0, Purpose.REPLAY)

    # -- the relabeler -------------------------------------------------------------------------------
    @property
    def relabeler(self) -> RelabelerSeeds:
        return RelabelerSeeds(*(self.integer(Role.RELABELER, 0, p) for p in (
            Purpose.RELABEL_DRAWS, Purpose.GENERATOR_INIT, Purpose.DATASET_SPLIT, Purpose.GENERATOR_BATCHES)))

    # -- actors --------------------------------------------------------------------------------------
    def actor_torch(self, actor: int) -> int:
        return self.integer(Role.ACTOR, actor, Purpose.TORCH)

    def actor_exploration(self, actor: int) -> int:
        return self.integer(Role.ACTOR, actor, Purpose.EXPLORATION)

    def actor_env_seeds(self, actor: int, n_envs: int) -> list[int]:
        """One seed per environment of actor `actor` (a world's `env_seeds`)."""
        return self.integers(Role.ACTOR, actor, Purpose.ENVS, n_envs)

    # -- evaluation ----------------------------------------------------------------------------------
    def evaluation_env_seeds(self, frames: int, episodes: int) -> list[int]:
        """One seed per evaluation episode at `frames` learner frames: fresh goals at every evaluation,
        the same ones for every policy scored at that count."""
        return self.integers(Role.EVALUATION, int(frames), Purpose.EPISODES, episodes)


def rng_state_to_array(rng: np.random.Generator) -> np.ndarray:
    """The generator's PCG64 state as 6 uint64 words, so a checkpoint needs no pickled dict."""
    s = rng.bit_generator.state
    if s["bit_generator"] != "PCG64":
        raise ValueError(f"cannot store a {s['bit_generator']} generator state")
    mask = (1 << 64) - 1
    state, inc = s["state"]["state"], s["state"]["inc"]
    return np.array([state >> 64, state & mask, inc >> 64, inc & mask, s["has_uint32"], s["uinteger"]],
                    dtype=np.uint64)


def rng_state_from_array(rng: np.random.Generator, words: np.ndarray) -> None:
    """Set the generator to the PCG64 state `rng_state_to_array` wrote."""
    w = [int(x) for x in np.asarray(words, dtype=np.uint64)]
    rng.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
        "has_uint32": w[4], "uinteger": w[5],
    }
