"""Epsilon-greedy exploration: Ape-X per-slot epsilons or the paper's linear decay.

Ape-X (Horgan et al. 2018) gives exploring process i of N the fixed rate eps^(1 + alpha*i/(N-1)).
Here the N "processes" are all env slots of all actors (n_actors * n_envs), not the actors: with only
a couple of actors, one epsilon per actor would leave the whole system exploring at one or two rates,
while spreading the ladder over the env slots lets even a single actor act at many rates at once.
Slots are dealt round-robin (env j of actor a gets rung j*n_actors + a), so every actor gets a spread
from the most to the least exploratory rungs rather than one actor getting all the greedy ones.
"""
from __future__ import annotations

import numpy as np

from higher_dist.config import ExplorationConfig

__all__ = ["apex_epsilons", "linear_schedule", "linear_epsilon", "actor_epsilons", "epsilon_greedy",
           "Explorer", "zeta_durations"]


def apex_epsilons(n: int, eps_base: float, alpha: float) -> np.ndarray:
    """eps_i = eps_base ** (1 + alpha * i / (n - 1)) for i in 0..n-1; [eps_base] when n == 1."""
    if n < 1:
        raise ValueError(f"apex_epsilons needs n >= 1, got {n}")
    if n == 1:
        return np.array([eps_base], dtype=np.float64)
    return float(eps_base) ** (1.0 + alpha * np.arange(n, dtype=np.float64) / (n - 1))


def linear_schedule(x: float, start: float, end: float, span: float) -> float:
    """start at x=0, end at x=span and after, linear in between (end at once when span <= 0)."""
    if span <= 0:
        return float(end)
    frac = min(1.0, max(0.0, x / span))
    return float(start + frac * (end - start))


def linear_epsilon(frame: int, cfg: ExplorationConfig) -> float:
    """eps_start at frame 0, eps_end at decay_frames and after, linear in between."""
    return linear_schedule(frame, cfg.eps_start, cfg.eps_end, cfg.decay_frames)


def actor_epsilons(cfg: ExplorationConfig, actor_index: int, n_actors: int, n_envs: int,
                   frame: int) -> np.ndarray:
    """The epsilon of each of one actor's n_envs environments, shape (n_envs,).

    apex: fixed rungs of a ladder spread over all n_actors * n_envs env slots (see the module notes),
    reached linearly from 1.0 over the first `warmup_frames` of `frame` (the run's env frames).
    linear: every env uses the decayed epsilon at `frame`.
    """
    if not 0 <= actor_index < n_actors:
        raise ValueError(f"actor_index must be in [0, {n_actors}), got {actor_index}")
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs}")
    if cfg.kind == "apex":
        ladder = apex_epsilons(n_actors * n_envs, cfg.eps_base, cfg.apex_alpha)
        rungs = ladder[np.arange(n_envs) * n_actors + actor_index]
        if cfg.warmup_frames > 0 and frame < cfg.warmup_frames:
            rungs = rungs + (1.0 - rungs) * (1.0 - frame / cfg.warmup_frames)
        return rungs
    if cfg.kind == "linear":
        return np.full(n_envs, linear_epsilon(frame, cfg), dtype=np.float64)
    raise ValueError(f"unknown exploration kind {cfg.kind!r}; choose apex or linear")


def epsilon_greedy(q_values: np.ndarray, eps: np.ndarray | float, rng: np.random.Generator) -> np.ndarray:
    """Per row: a uniform random action with probability eps[b], else argmax (first on ties)."""
    q = np.asarray(q_values)
    if q.ndim != 2:
        raise ValueError(f"q_values must be (B, A), got shape {q.shape}")
    batch, n_actions = q.shape
    eps = np.broadcast_to(np.asarray(eps, dtype=np.float64), (batch,))
    greedy = q.argmax(axis=1)
    explore = rng.random(batch) < eps
    random_actions = rng.integers(0, n_actions, size=batch)
    return np.where(explore, random_actions, greedy).astype(np.int64)


def zeta_durations(repeat_max: int, mu: float) -> tuple[np.ndarray, np.ndarray]:
    """Durations 1..repeat_max and their probabilities, p(n) proportional to n ** -mu."""
    if repeat_max < 1 or mu <= 0:
        raise ValueError(f"zeta_durations needs repeat_max >= 1 and mu > 0, got {repeat_max}, {mu}")
    n = np.arange(1, repeat_max + 1, dtype=np.float64)
    p = n ** -float(mu)
    return n.astype(np.int64), p / p.sum()


class Explorer:
    """Epsilon-greedy over a batch of environments, optionally temporally extended (ez-greedy).

    With repeat_max = 1 every step is an independent epsilon-greedy choice (`epsilon_greedy`, same random
    draws). With repeat_max > 1, an environment that is not already exploring starts with probability
    eps[b] an exploratory run: a uniform action held for n ~ zeta(mu) steps (capped), after which the
    greedy policy resumes. A run never outlives its episode: call `episodes_ended` after each step.
    """

    def __init__(self, n_envs: int, n_actions: int, repeat_max: int = 1, mu: float = 2.0):
        self.n_actions = n_actions
        self.repeat_max = repeat_max
        self.durations, self.duration_p = zeta_durations(repeat_max, mu)
        self.held = np.zeros(n_envs, np.int64)
        self.left = np.zeros(n_envs, np.int64)  # steps of the current exploratory run still to act

    def __call__(self, q_values: np.ndarray, eps: np.ndarray | float, rng: np.random.Generator) -> np.ndarray:
        if self.repeat_max == 1:
            return epsilon_greedy(q_values, eps, rng)
        q = np.asarray(q_values)
        batch = q.shape[0]
        if batch != self.left.shape[0]:
            raise ValueError(f"q_values has {batch} rows for an explorer of {self.left.shape[0]} envs")
        eps = np.broadcast_to(np.asarray(eps, dtype=np.float64), (batch,))
        holding = self.left > 0
        start = ~holding & (rng.random(batch) < eps)
        n_start = int(start.sum())
        if n_start:  # draws only for the runs that start
            self.held[start] = rng.integers(0, self.n_actions, size=n_start)
            self.left[start] = rng.choice(self.durations, size=n_start, p=self.duration_p)
        exploring = holding | start
        self.left = np.where(exploring, self.left - 1, 0)
        return np.where(exploring, self.held, q.argmax(axis=1)).astype(np.int64)

    def episodes_ended(self, ended: np.ndarray) -> None:
        """Stop the exploratory runs of the environments whose episode just ended."""
        self.left[np.asarray(ended, dtype=bool)] = 0
