"""The single-process runner: actors, relabeler and learner as one synchronous loop.

Every part comes from `AgentBuilder`, the one the cluster's roles use, with the same seeds and cadences
(epsilon driven by the learner's frame count, the generator's training pace per env frame, evaluation
every `cfg.eval.every_frames`, policy refresh every `cfg.weights_every` updates), so a bug seen in the
cluster can be reproduced here, under a debugger, deterministically.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.learning.acting import act
from higher_dist.learning.agent import AgentBuilder, train_generator
from higher_dist.learning.compiled_loss import TRACING_GATE
from higher_dist.learning.hindsight.relabel import relabel_batch


class SingleProcessRunner:
    def __init__(self, cfg: Config, log: Callable[[dict], None] | None = None):
        self.cfg = cfg
        self.agent = AgentBuilder(cfg)
        torch.manual_seed(self.agent.seeds.learner_torch)  # the learner's process RNG: this is its process
        self.log = log or (lambda record: None)
        self.core = self.agent.learner()
        self.relabeler = self.agent.relabel_strategy()
        self.pace = self.agent.generator_pace()
        self.collectors = [self.agent.collector(i) for i in range(cfg.actors)]
        self.rngs = [self.agent.exploration_rng(i) for i in range(cfg.actors)]
        self.explorers = [self.agent.explorer(c.n_envs) for c in self.collectors]
        self.policy = self.agent.policy()
        self.eval_policy = self.agent.policy()  # evaluation loads the learner's current weights here
        self.weights_version = 0
        self.frames_done = 0  # env frames stepped by this run, across resumes
        self.elapsed_s = 0.0  # seconds of running before this process (a resumed run's clock goes on)
        self._sync_policy()

    # -- checkpoints: what a resumed run needs to go on as if it had not stopped -----------------------
    def state_dict(self) -> dict:
        """The learner (replay included when `replay.checkpoint_replay`), the relabeler, the generator's
        pace, the exploration generators and the run's clocks. Episodes in flight are not kept: a resumed
        run starts fresh episodes, as a restarted actor does."""
        return {"core": self.core.state_dict(with_replay=self.cfg.replay.checkpoint_replay),
                "relabeler": self.relabeler.state_dict(), "pace": self.pace.state_dict(),
                "rngs": [rng.bit_generator.state for rng in self.rngs], "torch_rng": torch.get_rng_state(),
                "frames_done": self.frames_done, "elapsed_s": self.elapsed_s, "config": self.cfg.to_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.core.load_state_dict(state["core"])
        self.relabeler.load_state_dict(state["relabeler"])
        self.pace.load_state_dict(state["pace"])
        for rng, saved in zip(self.rngs, state["rngs"]):
            rng.bit_generator.state = saved
        torch.set_rng_state(state["torch_rng"])
        self.frames_done, self.elapsed_s = int(state["frames_done"]), float(state["elapsed_s"])
        self._sync_policy()

    def _sync_policy(self) -> None:
        self.policy.load(self.core.dqn.weights_numpy())
        self.weights_version = self.core.updates
        for c in self.collectors:
            c.weights_version = self.weights_version

    def run(self, frames: int | None = None, metrics_every: int = 10_000,
            checkpoint: Callable[[], None] | None = None, checkpoint_every_s: float = 300.0,
            stop: Callable[[], bool] = lambda: False) -> dict:
        """Act and learn until `frames` env frames in all (default: the config's budget) or until `stop()`
        says so between rounds; a resumed run goes on from its `frames_done`. `checkpoint` is called every
        `checkpoint_every_s` and when the loop ends."""
        budget = frames if frames is not None else self.cfg.frames
        frames_done = self.frames_done
        next_metrics = (frames_done // metrics_every + 1) * metrics_every
        evaluation = self.agent.evaluation_cadence(self.core.frames)
        start = time.perf_counter() - self.elapsed_s
        last_checkpoint = time.perf_counter()
        record: dict = {}
        last_eval: dict = {}
        while frames_done < budget and not stop():
            # Every module call of a round waits out a background compile's trace (compiled_loss.py).
            with TRACING_GATE.using():
                for i, collector in enumerate(self.collectors):
                    eps = self.agent.epsilons(i, collector.n_envs, self.core.frames)
                    episodes = act(collector, self.policy, eps, self.rngs[i], self.explorers[i])
                    frames_done += collector.n_envs
                    if episodes:
                        self._handle(episodes)
                before = self.core.updates
                self.core.train_available(max_updates=10_000)
                if self.agent.weights_due(before, self.core.updates):
                    self._sync_policy()
                # On the cadence, and once at the end: the run's last point is greedy success at its end.
                if evaluation.due(self.core.frames) or frames_done >= budget:
                    last_eval = self.evaluate()
                if frames_done >= next_metrics or frames_done >= budget:
                    next_metrics += metrics_every
                    record = self.metrics(frames_done, time.perf_counter() - start)
                    record.update(last_eval)
                    self.log(record)
            self.frames_done, self.elapsed_s = frames_done, time.perf_counter() - start
            if checkpoint is not None and (frames_done >= budget or stop()
                                           or time.perf_counter() - last_checkpoint >= checkpoint_every_s):
                checkpoint()
                last_checkpoint = time.perf_counter()
        return record

    def _handle(self, episodes) -> None:
        stored, withheld = relabel_batch(self.relabeler, episodes)
        self.core.add_episodes(stored, withheld)
        self.pace.add_frames(sum(ep.length for ep in episodes))
        train_generator(self.relabeler, self.pace)

    def evaluate(self) -> dict:
        """Greedy success of the learner's current weights (and of their average, when kept), as the
        cluster's learner evaluates them."""
        dqn = self.core.dqn
        return self.agent.evaluate_weights(self.eval_policy, dqn.weights_numpy(), dqn.average_weights_numpy(),
                                           self.core.frames)

    def metrics(self, frames_done: int, elapsed: float) -> dict:
        record = self.core.metrics()
        record.update(self.relabeler.metrics())
        record.update({
            m.FRAMES: frames_done, m.REJECTED: 0, m.PRESET: self.cfg.preset,
            m.WORLD: self.cfg.world.name, m.FRAMES_BUDGET: self.cfg.frames,
            m.ELAPSED_S: round(elapsed, 1),
            m.FRAMES_PER_S: round(frames_done / max(elapsed, 1e-9), 1),
            m.UPDATES_PER_S: round(self.core.updates / max(elapsed, 1e-9), 2),
            m.EPSILON_MEAN: float(np.mean(self.agent.epsilons(0, self.cfg.envs_per_actor, self.core.frames))),
        })
        return record
