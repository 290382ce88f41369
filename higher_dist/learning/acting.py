"""Acting: a batched world, an epsilon-greedy policy and the bookkeeping that turns steps into episodes.

The collector keeps, per environment, the frames, actions and rewards of the running episode in
preallocated arrays (no per-step Python lists), and the last `frame_stack` views as the policy's input.
The same collector serves the cluster's actors, the single-process runner and evaluation.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import torch

from higher_dist import metrics as m
from higher_dist.config import NetworkConfig, WorldConfig
from higher_dist.learning.episode import SUCCESS, Episode
from higher_dist.learning.episode_ends import classify, judged_stack
from higher_dist.learning.exploration import Explorer, epsilon_greedy
from higher_dist.learning.devices import resolve_device
from higher_dist.learning.networks import load_weights_numpy
from higher_dist.learning.recurrent import q_network
from higher_dist.world.batched import batched_world
from higher_dist.world.spec import DEFAULT_SPEC, RUNNING, WorldSpec

QFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]


class EpisodeCollector:
    def __init__(self, world_cfg: WorldConfig, n_envs: int, frame_stack: int, seed: int = 0,
                 actor_id: int = 0, goal_set: str = "train", env_seeds=None):
        """Env i is seeded from [seed, i], or from `env_seeds[i]` when given (see world/batched.py)."""
        self.world = batched_world(world_cfg, n_envs, seed, goal_set=goal_set, env_seeds=env_seeds)
        self.n_envs, self.frame_stack, self.actor_id = n_envs, frame_stack, actor_id
        v = self.world.view_size
        t_max = self.world.max_steps
        self._frames = np.zeros((n_envs, t_max + 1, v, v, 4), np.uint8)
        self._actions = np.zeros((n_envs, t_max), np.uint8)
        self._rewards = np.zeros((n_envs, t_max), np.float32)
        self._t = np.zeros(n_envs, np.int64)
        self._rows = np.arange(n_envs)
        view, mission = self.world.reset()
        self.mission = mission  # the world never edits arrays it handed out
        self._frames[:, 0] = view
        self.stack = np.repeat(view[:, None], frame_stack, axis=1)
        self.weights_version = 0
        self.last_outcome = np.full(n_envs, RUNNING, np.int8)  # per env, of the last step

    def observation(self) -> tuple[np.ndarray, np.ndarray]:
        """The policy's input: (B, k, V, V, 4) uint8 frame stacks and (B, L) mission tokens."""
        return self.stack, self.mission

    def starts(self) -> np.ndarray:
        """(B,) bool: the environments whose current view is their episode's first (a recurrent policy
        starts its state afresh there)."""
        return self._t == 0

    def step(self, actions: np.ndarray) -> list[Episode]:
        """Step every environment once; return the episodes that finished on this step."""
        res = self.world.step(actions)
        self.last_outcome = res.outcome
        rows = self._rows
        self._actions[rows, self._t] = actions
        self._rewards[rows, self._t] = res.reward
        self._t += 1
        self._frames[rows, self._t] = res.final_view
        done = np.flatnonzero(res.done)
        finished = [self._episode(i, res) for i in done]
        # Shift the frame stacks; a fresh episode starts with its first view repeated.
        self.stack[:, :-1] = self.stack[:, 1:]
        self.stack[:, -1] = res.view
        if done.size:
            self.stack[done] = res.view[done, None]
            self._t[done] = 0
            self._frames[done, 0] = res.view[done]
        self.mission = res.mission
        return finished

    def _episode(self, i: int, res) -> Episode:
        t = int(self._t[i])
        return Episode(
            frames=self._frames[i, : t + 1].copy(), actions=self._actions[i, :t].copy(),
            rewards=self._rewards[i, :t].copy(), mission=res.mission_done[i].astype(np.int64),
            outcome=int(res.outcome[i]), picked=res.picked[i].astype(np.int8),
            goal=res.goal[i].astype(np.int8), pick_step=int(res.pick_step[i]), actor_id=self.actor_id,
            weights_version=self.weights_version,
            later_achieved=None if res.later_achieved is None else res.later_achieved[i].copy(),
            later_step=None if res.later_step is None else res.later_step[i].copy(),
        )


class TorchQFunction:
    """Batched greedy Q-values from a QNetwork whose weights arrive as numpy arrays (actors, eval)."""

    recurrent = False  # called as (obs, mission); a recurrent policy also takes the episode starts

    def __init__(self, net_cfg: NetworkConfig, spec: WorldSpec = DEFAULT_SPEC, device: str = "cpu"):
        self.device = resolve_device(device)
        self.net = q_network(net_cfg, spec).to(self.device).eval()

    def load(self, arrays: dict[str, np.ndarray]) -> None:
        load_weights_numpy(self.net, arrays)

    @torch.no_grad()
    def __call__(self, obs: np.ndarray, mission: np.ndarray) -> np.ndarray:
        o = torch.from_numpy(np.ascontiguousarray(obs)).to(self.device)
        m = torch.from_numpy(np.ascontiguousarray(mission)).long().to(self.device)
        return self.net(o, m).float().cpu().numpy()


class RecurrentQFunction(TorchQFunction):
    """A recurrent Q-network (network.core=gru) stepped one view at a time, with a state per environment
    that starts at zero on each episode's first view, as the learner unrolls episodes from their start.
    New weights apply from the next step; the running state is kept."""

    recurrent = True

    def __init__(self, net_cfg: NetworkConfig, spec: WorldSpec = DEFAULT_SPEC, device: str = "cpu"):
        super().__init__(net_cfg, spec, device)
        self.state: torch.Tensor | None = None  # (1, B, hidden)

    @torch.no_grad()
    def __call__(self, obs: np.ndarray, mission: np.ndarray, starts: np.ndarray | None = None) -> np.ndarray:
        """Q-values (B, A) of views `obs` (B, 1, V, V, 4); `starts` (B,) bool marks first views (None:
        all are). A batch of another size than the state's must be all first views."""
        b = obs.shape[0]
        starts = np.ones(b, bool) if starts is None else np.asarray(starts, bool)
        if starts.shape != (b,):
            raise ValueError(f"starts: expected ({b},) flags, got {starts.shape}")
        if self.state is None or self.state.shape[1] != b:
            if not starts.all():
                raise ValueError(f"a recurrent policy got {b} environments mid-episode, its state holds "
                                 f"{0 if self.state is None else self.state.shape[1]}")
            self.state = torch.zeros(1, b, self.net.cfg.hidden, device=self.device)
        elif starts.any():
            self.state[:, torch.from_numpy(starts).to(self.device)] = 0.0
        o = torch.from_numpy(np.ascontiguousarray(obs)).to(self.device)
        m = torch.from_numpy(np.ascontiguousarray(mission)).long().to(self.device)
        q, self.state = self.net.q_sequence(o, self.net.encode_mission(m), self.state)
        return q[:, 0].float().cpu().numpy()


def make_policy(net_cfg: NetworkConfig, spec: WorldSpec = DEFAULT_SPEC, device: str = "cpu") -> TorchQFunction:
    """The acting policy for `net_cfg`'s core."""
    kind = RecurrentQFunction if net_cfg.recurrent else TorchQFunction
    return kind(net_cfg, spec, device=device)


def q_values(q_fn: QFunction, collector: EpisodeCollector) -> np.ndarray:
    """`q_fn` on the collector's current input (with the episode starts, for a recurrent policy)."""
    obs, mission = collector.observation()
    if getattr(q_fn, "recurrent", False):
        return q_fn(obs, mission, starts=collector.starts())
    return q_fn(obs, mission)


def act(collector: EpisodeCollector, q_fn: QFunction, eps: np.ndarray, rng: np.random.Generator,
        explorer: Explorer | None = None) -> list[Episode]:
    """One epsilon-greedy step of every environment of the collector (temporally extended when the
    explorer holds exploratory actions over several steps)."""
    choose = explorer or epsilon_greedy  # the same call: (q_values, eps, rng) -> actions
    episodes = collector.step(choose(q_values(q_fn, collector), eps, rng))
    if explorer is not None:
        explorer.episodes_ended(collector.last_outcome != RUNNING)
    return episodes


def first_episodes(q_fn: QFunction, world_cfg: WorldConfig, frame_stack: int, goal_set: str, env_seeds: Sequence[int],
                   n_envs: int = 256, epsilon: float = 0.0, rng: np.random.Generator | None = None) -> list[Episode]:
    """One episode per seed of `env_seeds`, whose goals come from `goal_set` (train|heldout), played by
    `q_fn` greedily (first on ties, as epsilon_greedy), or with a random action with probability
    `epsilon` (drawn from `rng`).

    Exactly one episode per environment: the environments (in batches of at most `n_envs`) each run
    their first episode to its end, and only that episode counts. Keeping the first episodes to finish
    instead would over-count short ones (successes end early, time-outs last the whole step limit),
    biasing a success rate upwards.
    """
    if len(env_seeds) < 1:
        raise ValueError(f"env_seeds: needs at least one seed (one per episode), got {len(env_seeds)}")
    if epsilon > 0 and rng is None:
        raise ValueError("first_episodes: epsilon > 0 needs an rng")
    out: list[Episode] = []
    for start in range(0, len(env_seeds), n_envs):
        batch_seeds = list(env_seeds[start:start + n_envs])
        collector = EpisodeCollector(world_cfg, len(batch_seeds), frame_stack, goal_set=goal_set, env_seeds=batch_seeds)
        first: list[Episode | None] = [None] * len(batch_seeds)
        while any(ep is None for ep in first):
            q = q_values(q_fn, collector)
            finished = collector.step(epsilon_greedy(q, epsilon, rng) if epsilon > 0 else q.argmax(axis=1))
            # The collector lists the episodes that ended on this step in environment order.
            for i, ep in zip(np.flatnonzero(collector.last_outcome != RUNNING), finished):
                if first[i] is None:
                    first[i] = ep
        out.extend(first)
    return out


def evaluate(q_fn: QFunction, world_cfg: WorldConfig, frame_stack: int, goal_set: str, env_seeds: Sequence[int],
             n_envs: int = 256) -> tuple[float, float]:
    """Greedy success rate over one episode per seed of `env_seeds` (Seeds.evaluation_env_seeds), whose
    goals come from `goal_set` (train|heldout), and its standard error (first_episodes)."""
    rate, se, _ = _rates(first_episodes(q_fn, world_cfg, frame_stack, goal_set, env_seeds, n_envs), frame_stack)
    return rate, se


def _rates(episodes: list[Episode], frame_stack: int) -> tuple[float, float, float]:
    """(success rate, its standard error, the share of episodes that ended in a cycle)."""
    n = len(episodes)
    rate = sum(ep.outcome == SUCCESS for ep in episodes) / n
    cycling = sum(classify(ep, frame_stack) == "cycling" for ep in episodes) / n
    return rate, math.sqrt(rate * (1.0 - rate) / n), cycling


def evaluate_goal_sets(q_fn: QFunction, cfg, env_seeds: Sequence[int], suffix: str = "") -> dict[str, float]:
    """The periodic evaluation of a run (`cfg`: Config): greedy success on training and held-out goals,
    each with its standard error (`_se`) and the share of episodes that ended in a cycle
    (learning/episode_ends.py), one episode per seed of `env_seeds` in each goal set.
    `suffix` names another policy scored on the same goals (metrics.AVERAGED_SUFFIX for the averaged
    weights)."""
    k, judged = cfg.network.frame_stack, judged_stack(cfg.network.frame_stack, cfg.network.core)
    out: dict[str, float] = {}
    goal_sets = [("train", m.SUCCESS_EVAL_TRAIN, m.CYCLING_EVAL_TRAIN)]
    if WorldSpec.of(cfg.world).has_heldout:  # a BabyAI level is scored on its own missions only
        goal_sets.append(("heldout", m.SUCCESS_EVAL_HELDOUT, m.CYCLING_EVAL_HELDOUT))
    for goal_set, key, cycling_key in goal_sets:
        rate, se, cycling = _rates(first_episodes(q_fn, cfg.world, k, goal_set, env_seeds), judged)
        out[key + suffix] = round(rate, 4)
        out[key + suffix + m.SE_SUFFIX] = round(se, 4)
        out[cycling_key + suffix] = round(cycling, 4)
    return out
