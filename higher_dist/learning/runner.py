"""The single-process runner: actors, relabeler and learner as one synchronous loop.

It drives exactly the components the cluster's roles wrap (EpisodeCollector, a relabel strategy,
LearnerCore), so a bug seen in the cluster can be reproduced here, under a debugger, deterministically.
Policy weights are copied from the learner every `cfg.weights_every` updates, as the cluster publishes.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from higher_dist.config import Config
from higher_dist.learning.acting import EpisodeCollector, TorchQFunction, act, evaluate_goal_sets
from higher_dist.learning.exploration import actor_epsilons
from higher_dist.learning.learner_core import LearnerCore, relabel_record
from higher_dist.learning.relabel import make_relabeler

GENERATOR_ROUND_FRAMES = 1000


class SingleProcessRunner:
    def __init__(self, cfg: Config, log: Callable[[dict], None] | None = None):
        torch.manual_seed(cfg.seed)
        self.cfg = cfg
        self.log = log or (lambda record: None)
        self.core = LearnerCore(cfg)
        self.relabeler = make_relabeler(cfg, seed=cfg.seed + 1)
        self.collectors = [
            EpisodeCollector(cfg.world, cfg.envs_per_actor, cfg.network.frame_stack,
                             seed=cfg.seed * 1000 + 17 * (i + 1), actor_id=i)
            for i in range(cfg.actors)
        ]
        self.policy = TorchQFunction(cfg.network, device="cpu")
        self.rng = np.random.default_rng(cfg.seed)
        self.weights_version = 0
        self._frames_since_generator_round = 0
        self._sync_policy()

    def _sync_policy(self) -> None:
        self.policy.load(self.core.dqn.weights_numpy())
        self.weights_version = self.core.updates
        for c in self.collectors:
            c.weights_version = self.weights_version

    def run(self, frames: int | None = None, metrics_every: int = 10_000) -> dict:
        budget = frames if frames is not None else self.cfg.frames
        frames_done = 0
        next_metrics, next_eval = metrics_every, self.cfg.eval.every_frames
        start = time.perf_counter()
        record: dict = {}
        while frames_done < budget:
            for i, collector in enumerate(self.collectors):
                eps = actor_epsilons(self.cfg.exploration, i, self.cfg.actors, collector.n_envs,
                                     self.core.frames)
                episodes = act(collector, self.policy, eps, self.rng)
                frames_done += collector.n_envs
                self._frames_since_generator_round += collector.n_envs
                if episodes:
                    self._handle(episodes)
            before = self.core.updates
            self.core.train_available(max_updates=10_000)
            if self.core.updates // self.cfg.weights_every != before // self.cfg.weights_every:
                self._sync_policy()
            if frames_done >= next_metrics or frames_done >= budget:
                next_metrics += metrics_every
                record = self.metrics(frames_done, time.perf_counter() - start)
                if frames_done >= next_eval:
                    next_eval += self.cfg.eval.every_frames
                    record.update(self.evaluate())
                self.log(record)
        return record

    def _handle(self, episodes) -> None:
        self.relabeler.observe(episodes)
        copies = self.relabeler.relabel(episodes)
        self.core.add_episodes(episodes + copies)
        # One generator round per GENERATOR_ROUND_FRAMES env frames, as the relabeler service paces it.
        if self._frames_since_generator_round >= GENERATOR_ROUND_FRAMES:
            self._frames_since_generator_round = 0
            self.relabeler.train(self.cfg.generator.train_steps_per_round)

    def evaluate(self) -> dict:
        return evaluate_goal_sets(self.policy, self.cfg, seed=self.cfg.seed + 10_000 + self.core.updates)

    def metrics(self, frames_done: int, elapsed: float) -> dict:
        record = self.core.metrics()
        record.update(relabel_record(self.relabeler.metrics()))
        record.update({
            "frames": frames_done, "rejected_messages": 0, "preset": self.cfg.preset,
            "world": self.cfg.world.name, "frames_budget": self.cfg.frames,
            "frames_per_s": round(frames_done / max(elapsed, 1e-9), 1),
            "updates_per_s": round(self.core.updates / max(elapsed, 1e-9), 2),
            "epsilon_mean": float(np.mean(actor_epsilons(self.cfg.exploration, 0, self.cfg.actors,
                                                         self.cfg.envs_per_actor, self.core.frames))),
        })
        return record
