"""One builder of the agent, used by the single-process runner and by every role of the cluster.

It makes the components (the learner core, the relabel strategy, the actors' collectors and policies),
derives every seed from `cfg.seed` (through `Seeds`, learning/seeds.py), and owns the cadences (greedy
evaluation, generator training pace, the frame count that drives epsilon), so that the runner really
is the cluster in one process: a difference between the two is a bug in one place, not two drifting
copies.
"""
from __future__ import annotations

import numpy as np

from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.learning.acting import EpisodeCollector, TorchQFunction, evaluate_goal_sets, make_policy
from higher_dist.learning.exploration import Explorer, actor_epsilons
from higher_dist.learning.learner import Learner
from higher_dist.learning.hindsight.relabel import RelabelStrategy, make_relabel_strategy
from higher_dist.learning.seeds import Seeds
from higher_dist.world.spec import WorldSpec


class Cadence:
    """Fires once each time a counter passes a multiple of `every` (evaluation every N frames, ...)."""

    def __init__(self, every: int, start: int = 0):
        self.every = max(1, int(every))
        self.next = (int(start) // self.every + 1) * self.every

    def due(self, count: int) -> bool:
        if count < self.next:
            return False
        self.next = (int(count) // self.every + 1) * self.every
        return True


class GeneratorPace:
    """Generator updates owed for the env frames seen: `generator.updates_per_kframe` per 1000 frames.

    The runner and the relabeler service both feed it the frames of the original episodes they handle
    and train what it says is owed, so the generator gets the same training per frame whatever the
    machine's speed. Updates that cannot run yet (too few pairs for a batch) are forgiven, not banked.

    Each frame earns the pace of the state the generator was in when it came (`follow` sets it from the
    latest measurement and the gate, both ways):
    - gate shut, with `gated_updates_per_kframe` > 0: that pace. The relabeler has nothing to relabel
      then, and the gate opens at the first measurement after enough updates on enough pairs;
    - `trained_accuracy` > 0 and the validation exact match at or above it: `trained_updates_per_kframe`.
      Early on the generator learns from a few pairs many times over and needs every update, later it
      is right and the relabeler's core is better spent on the rest of the run;
    - otherwise `updates_per_kframe`.
    """

    def __init__(self, updates_per_kframe: float, trained_accuracy: float = 0.0,
                 trained_updates_per_kframe: float | None = None, gated_updates_per_kframe: float = 0.0):
        self.rate = float(updates_per_kframe) / 1000.0
        trained = updates_per_kframe if trained_updates_per_kframe is None else trained_updates_per_kframe
        self.trained_rate = float(trained) / 1000.0
        self.trained_accuracy = float(trained_accuracy)
        self.gated_rate = float(gated_updates_per_kframe) / 1000.0
        self.trained = False  # the generator's latest measurement is at trained_accuracy or above
        self.gated = self.gated_rate > 0  # the gate is shut (it starts shut) and has its own pace
        self.frames = 0
        self.frames_trained = 0  # of `frames`, those seen while trained (and the gate open)
        self.frames_gated = 0  # of `frames`, those seen while the gate was shut, at the gated pace
        self.settled = 0  # updates done or forgiven

    @property
    def follows(self) -> bool:
        """Whether the pace depends on the generator's state at all."""
        return self.trained_accuracy > 0 or self.gated_rate > 0

    def add_frames(self, frames: int) -> None:
        self.frames += int(frames)
        if self.gated:
            self.frames_gated += int(frames)
        elif self.trained:
            self.frames_trained += int(frames)

    def follow(self, accuracy: float | None, gate_open: bool | None = None) -> None:
        """The generator's latest validation exact match (None: not measured yet) and whether its gate is
        open (None: it has none) set the pace of the frames to come."""
        self.trained = self.trained_accuracy > 0 and accuracy is not None and accuracy >= self.trained_accuracy
        self.gated = self.gated_rate > 0 and gate_open is False

    @property
    def owed(self) -> int:
        plain = self.frames - self.frames_trained - self.frames_gated
        earned = plain * self.rate + self.frames_trained * self.trained_rate + self.frames_gated * self.gated_rate
        return max(0, int(earned) - self.settled)

    @property
    def updates_per_kframe(self) -> float:
        """The pace the frames to come earn."""
        return 1000.0 * (self.gated_rate if self.gated else self.trained_rate if self.trained else self.rate)

    def settle(self, updates: int) -> None:
        self.settled += int(updates)

    def state_dict(self) -> dict:
        return {"frames": self.frames, "settled": self.settled, "frames_trained": self.frames_trained,
                "trained": self.trained, "frames_gated": self.frames_gated, "gated": self.gated}

    def load_state_dict(self, state: dict) -> None:
        self.frames, self.settled = int(state["frames"]), int(state["settled"])
        self.frames_trained, self.trained = int(state.get("frames_trained", 0)), bool(state.get("trained", False))
        self.frames_gated = int(state.get("frames_gated", 0))
        self.gated = bool(state.get("gated", self.gated_rate > 0 and self.frames_gated == self.frames))


def train_generator(strategy: RelabelStrategy, pace: GeneratorPace, max_updates: int | None = None) -> int:
    """Run the updates `pace` says are owed (at most `max_updates`); returns how many were settled."""
    owed = pace.owed if max_updates is None else min(pace.owed, max_updates)
    if owed <= 0:
        return 0
    ran = strategy.train(owed)
    # An empty result means the strategy could not train yet (no generator, or too few pairs).
    pace.settle(owed)
    if pace.follows:  # only a pace that depends on it asks for the generator's state
        pace.follow(strategy.generator_accuracy, strategy.gate_open)
    return owed if ran else 0


class AgentBuilder:
    """Makes the parts of one run from its config; the runner and the roles call only this."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.spec = WorldSpec.of(cfg.world)
        self.seeds = Seeds(cfg.seed)

    # -- components --------------------------------------------------------------------------------
    def learner(self, device: str | None = None) -> Learner:
        return Learner(self.cfg, device=device)

    def relabel_strategy(self) -> RelabelStrategy:
        return make_relabel_strategy(self.cfg, seed=self.seeds.relabeler)

    def generator_pace(self) -> GeneratorPace:
        g = self.cfg.generator
        return GeneratorPace(g.updates_per_kframe, g.trained_accuracy, g.trained_updates_per_kframe,
                             g.gated_updates_per_kframe)

    def collector(self, actor: int) -> EpisodeCollector:
        n_envs = self.cfg.envs_per_actor
        return EpisodeCollector(self.cfg.world, n_envs, self.cfg.network.frame_stack, actor_id=actor,
                                env_seeds=self.seeds.actor_env_seeds(actor, n_envs))

    def policy(self, device: str = "cpu") -> TorchQFunction:
        return make_policy(self.cfg.network, self.spec, device=device)

    def exploration_rng(self, actor: int) -> np.random.Generator:
        return np.random.default_rng(self.seeds.actor_exploration(actor))

    def explorer(self, n_envs: int) -> Explorer:
        e = self.cfg.exploration
        return Explorer(n_envs, self.spec.n_actions, e.repeat_max, e.repeat_mu)

    # -- cadences ----------------------------------------------------------------------------------
    def epsilons(self, actor: int, n_envs: int, learner_frames: int) -> np.ndarray:
        """Per-env epsilons of actor `actor`. `learner_frames`: the run's env frames as the learner counts
        them (original episodes only), the one clock for linear decay in the runner and the cluster."""
        return actor_epsilons(self.cfg.exploration, actor, self.cfg.actors, n_envs, learner_frames)

    def evaluation_cadence(self, start_frames: int = 0) -> Cadence:
        return Cadence(self.cfg.eval.every_frames, start_frames)

    def weights_due(self, updates_before: int, updates_after: int) -> bool:
        """Whether the policy should be refreshed (published, or copied in the runner)."""
        every = self.cfg.weights_every
        return updates_after // every != updates_before // every

    def evaluate(self, q_fn, frames: int, suffix: str = "") -> dict[str, float]:
        """Greedy success on training and held-out goals at `frames` learner frames (the same goals for
        every policy scored at that count; `suffix` names the policy's metrics, see evaluate_goal_sets)."""
        env_seeds = self.seeds.evaluation_env_seeds(frames, self.cfg.eval.episodes)
        return evaluate_goal_sets(q_fn, self.cfg, env_seeds, suffix=suffix)

    def evaluate_weights(self, q_fn, online: dict, averaged: dict | None, frames: int) -> dict[str, float]:
        """The periodic evaluation of a learner's weights, loaded into `q_fn` (an evaluation-only policy):
        the online weights, and on the same goals the averaged weights when the learner keeps them
        (dqn.average_tau > 0). Takes snapshots, so it can run off the learner's thread."""
        q_fn.load(online)
        out = self.evaluate(q_fn, frames)
        if averaged is not None:
            q_fn.load(averaged)
            out.update(self.evaluate(q_fn, frames, suffix=m.AVERAGED_SUFFIX))
        return out
