"""What the learner does, without any transport: take episodes into prioritized replay, run DQN updates
at the configured samples-per-insert ratio, and count what it saw. The single-process runner and the
cluster's learner role both drive this one object."""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.learning.compiled_loss import TRACING_GATE
from higher_dist.learning.dqn import DQNUpdater, learning_rate_at
from higher_dist.learning.episode import SUCCESS, Episode, Withheld
from higher_dist.learning.rate_limiter import SamplesPerInsertLimiter
from higher_dist.learning.replay import PrioritizedReplay
from higher_dist.learning.seeds import Seeds
from higher_dist.world.spec import WorldSpec


class Learner:
    def __init__(self, cfg: Config, device: str | None = None):
        self.cfg = cfg
        self.spec = WorldSpec.of(cfg.world)
        seeds = Seeds(cfg.seed)
        self.replay = PrioritizedReplay(cfg.replay, frame_stack=cfg.network.frame_stack, n_step=cfg.dqn.n_step,
                                        gamma=cfg.dqn.gamma, spec=self.spec, seed=seeds.learner_replay)
        self.dqn = DQNUpdater(cfg.network, cfg.dqn, device=device or cfg.device, spec=self.spec,
                              seed=seeds.learner_init)
        self.limiter = SamplesPerInsertLimiter(cfg.replay.samples_per_insert, cfg.replay.min_size)
        self.frames = 0  # env frames the actors reported (original episodes only)
        self.episodes = 0
        self.relabelled_episodes = 0
        self.recent_success: deque[int] = deque(maxlen=1000)  # training success over original episodes
        self.last_metrics: dict[str, float] = {}
        # dqn.prefetch: the next batch is sampled on this thread while the current update runs (numpy
        # and torch release the GIL in their kernels, so a second core overlaps them). Every other
        # replay access first waits for it (`_settle`), so the order of replay operations, and with it
        # the run, stays deterministic: batch n+1 is drawn right after batch n, before batch n's
        # priorities are written and before newer episodes arrive.
        self._prefetcher = ThreadPoolExecutor(1, thread_name_prefix="prefetch") if cfg.dqn.prefetch else None
        self._next_batch: Future | None = None

    @property
    def recurrent(self) -> bool:
        return self.cfg.network.recurrent

    @property
    def updates(self) -> int:
        return self.dqn.updates

    # -- experience -------------------------------------------------------------------------------
    def add_episodes(self, episodes: list[Episode], withheld: Withheld = Withheld()) -> None:
        """Store `episodes`; `withheld`: originals the relabeller kept out of the replay, counted as the
        actors played them (env frames, the replay ratio's inserts, training success: failures)."""
        self._settle()
        count_copies = self.cfg.replay.ratio_counts == "transitions"
        self.replay.add_episodes(episodes)  # all or none: a failure leaves the replay and the counts as they were
        if not count_copies:  # env frames, as the actors played them; stored transitions exclude these
            self.limiter.record_insert(withheld.frames)
        self.frames += withheld.frames
        self.episodes += withheld.episodes
        self.recent_success.extend([0] * withheld.episodes)
        for ep in episodes:
            # By default relabelled copies are stored but not counted: equal updates per env frame.
            if count_copies or not ep.relabelled:
                self.limiter.record_insert(ep.length)
            if ep.relabelled:
                self.relabelled_episodes += 1
            else:
                self.frames += ep.length
                self.episodes += 1
                self.recent_success.append(int(ep.outcome == SUCCESS))

    def wants_experience(self) -> bool:
        return self.limiter.can_insert()

    # -- learning ---------------------------------------------------------------------------------
    def can_update(self) -> bool:
        return self.limiter.can_sample(len(self.replay), self.cfg.dqn.batch_size)

    def update(self) -> dict[str, float]:
        """One prioritized DQN update; priorities come back from the loss as data."""
        if self._prefetcher is None:
            batch = self._sample()
        else:
            batch = self._next_batch.result() if self._next_batch is not None else self._sample()
            self._next_batch = self._prefetcher.submit(self._sample)
        if self.cfg.dqn.lr_decay_frames > 0:
            self.dqn.set_learning_rate(learning_rate_at(self.cfg.dqn, self.frames))
        priorities, metrics = self.dqn.update(batch, views_checked=True)  # the replay checked them on insert
        self._settle()
        self.replay.update_priorities(*batch.priority_update(priorities))
        self.limiter.record_sample(len(batch))  # transitions trained: whole episodes give a varying count
        self.last_metrics = metrics
        return metrics

    def _sample(self):
        beta = self.replay.beta_at(self.frames)
        if self.recurrent:
            return self.replay.sample_episodes(self.cfg.dqn.sequence_batch, beta)
        return self.replay.sample(self.cfg.dqn.batch_size, beta)

    def _settle(self) -> None:
        """Wait for an in-flight prefetch, so the replay is not read and written at once."""
        if self._next_batch is not None:
            self._next_batch.exception()  # waits; a failed sample re-raises at .result() in update

    def close(self) -> None:
        """Stop the prefetch thread (also safe to skip: it is idle between updates)."""
        self._settle()
        self._next_batch = None
        if self._prefetcher is not None:
            self._prefetcher.shutdown(wait=True)

    def train_available(self, max_updates: int) -> int:
        """Run updates while the ratio allows, at most `max_updates`; returns how many ran. None run
        while the loss compiles in the background (compiled_loss.TRACING_GATE): the caller goes on."""
        if not TRACING_GATE.try_enter():
            return 0
        try:
            n = 0
            while n < max_updates and self.can_update():
                self.update()
                n += 1
            return n
        finally:
            TRACING_GATE.leave()

    # -- reporting --------------------------------------------------------------------------------
    @property
    def success_rate_train(self) -> float:
        return float(np.mean(self.recent_success)) if self.recent_success else 0.0

    def metrics(self) -> dict[str, float]:
        out = {
            m.FRAMES: self.frames, m.UPDATES: self.updates, m.EPISODES: self.episodes,
            m.RELABELLED_EPISODES: self.relabelled_episodes,
            m.SUCCESS_TRAIN: round(self.success_rate_train, 4),
            m.REPLAY_SIZE: len(self.replay), m.REPLAY_RATIO: round(self.limiter.ratio, 3),
            m.LEARNING_RATE: self.dqn.learning_rate,
        }
        for origin, count in self.replay.composition().items():
            out[m.replay_origin(origin)] = int(count)
        out.update({k: round(float(v), 5) for k, v in self.last_metrics.items()})
        return out

    def state_dict(self, with_replay: bool = False) -> dict:
        # A prefetched batch is not part of the state: drop it, so the replay's RNG in the checkpoint
        # is the one the next update continues from (resume stays exact).
        self._settle()
        self._next_batch = None
        state = {
            "dqn": self.dqn.state_dict(), "limiter": self.limiter.state_dict(),
            "counters": {"frames": self.frames, "episodes": self.episodes, "updates": self.updates,
                         "relabelled_episodes": self.relabelled_episodes},
            "recent_success": list(self.recent_success),
        }
        if with_replay:
            state["replay"] = self.replay.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self._settle()
        self._next_batch = None
        self.dqn.load_state_dict(state["dqn"])
        self.limiter.load_state_dict(state["limiter"])
        c = state["counters"]
        self.frames, self.episodes = c["frames"], c["episodes"]  # updates: restored with the DQN
        self.relabelled_episodes = c["relabelled_episodes"]
        self.recent_success.extend(state.get("recent_success", []))
        if "replay" in state:
            self.replay.load_state_dict(state["replay"])
        else:
            # Without the replay the ratio restarts from an empty buffer.
            self.limiter.inserted = self.limiter.sampled = 0
