"""The acting loop: episodes assembled from batched steps, frame stacks, and evaluation goal sets."""
import numpy as np
import pytest
import torch

from higher_dist.config_presets import make_config, small_world
from higher_dist.learning.acting import EpisodeCollector, TorchQFunction, evaluate
from higher_dist.learning.dqn import DQNUpdater
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK
from higher_dist.learning.seeds import Seeds
from higher_dist.world.grid import ACTION_FORWARD, ACTION_LEFT, ACTION_PICK, KIND_EMPTY, KIND_KEY, BatchedFetchAttr
from higher_dist.world.language import VOCAB, parse
from higher_dist.world.objects import ObjectSpace


def collect(collector, n, rng):
    episodes = []
    while len(episodes) < n:
        episodes += collector.step(rng.integers(0, 4, size=collector.n_envs))
    return episodes


def as_set(attrs):
    return {tuple(int(v) for v in a) for a in attrs}


@pytest.mark.parametrize("goal_set", ["train", "heldout"])
def test_goals_come_from_the_goal_set_asked_for_and_only_from_it(goal_set):
    cfg = make_config("her", "paper").world
    space = ObjectSpace(cfg)
    collector = EpisodeCollector(cfg, 16, 4, seed=3, goal_set=goal_set)
    episodes = collect(collector, 200, np.random.default_rng(0))
    goals = as_set(ep.goal for ep in episodes)
    wanted = as_set(space.objects(goal_set))
    other = as_set(space.objects("heldout" if goal_set == "train" else "train"))
    assert goals <= wanted and not goals & other
    # The mission names the goal.
    assert all(tuple(parse(ep.mission)) == tuple(ep.goal) for ep in episodes)


def test_episodes_are_consistent_records_of_the_steps():
    cfg = small_world()
    collector = EpisodeCollector(cfg, 8, 3, seed=1)
    episodes = collect(collector, 100, np.random.default_rng(1))
    outcomes = {ep.outcome for ep in episodes}
    assert outcomes <= {SUCCESS, WRONG_PICK, TIMEOUT} and TIMEOUT in outcomes
    for ep in episodes:
        assert ep.frames.shape == (ep.length + 1, 7, 7, 4)
        assert ep.rewards.shape == ep.actions.shape == (ep.length,)
        assert 1 <= ep.length <= cfg.max_steps
        if ep.outcome == TIMEOUT:
            assert ep.length == cfg.max_steps and (ep.picked == -1).all() and ep.rewards.sum() == 0
        else:
            assert ep.actions[-1] == 3 and (ep.picked >= 0).all()
            assert ep.rewards[-1] == (1.0 if ep.outcome == SUCCESS else 0.0)


def test_frame_stack_holds_the_last_views_and_restarts_with_each_episode():
    cfg = small_world()
    collector = EpisodeCollector(cfg, 4, 3, seed=2)
    rng = np.random.default_rng(2)
    history = [collector.observation()[0][:, -1].copy()]
    for _ in range(30):
        collector.step(rng.integers(0, 3, size=4))  # no pick: only time-outs end episodes
        stack = collector.observation()[0]
        history.append(stack[:, -1].copy())
        for env in range(4):
            t = collector._t[env]
            if t >= 2:  # inside an episode the stack is the last three views in order
                assert (stack[env, 0] == history[-3][env]).all() and (stack[env, 1] == history[-2][env]).all()
            if t == 0:  # a fresh episode: its first view repeated
                assert (stack[env] == stack[env, -1]).all()


def test_greedy_evaluation_returns_a_rate_over_the_requested_episodes():
    torch.set_num_threads(1)
    cfg = make_config("her", "small")
    q = TorchQFunction(cfg.network)
    q.load(DQNUpdater(cfg.network, cfg.dqn).weights_numpy())
    env_seeds = Seeds(0).evaluation_env_seeds(0, 20)
    rate, se = evaluate(q, cfg.world, cfg.network.frame_stack, "heldout", env_seeds, n_envs=8)
    assert 0.0 <= rate <= 1.0 and se == pytest.approx((rate * (1 - rate) / 20) ** 0.5)
    assert (rate, se) == evaluate(q, cfg.world, cfg.network.frame_stack, "heldout", env_seeds, n_envs=8)


def seek_goal_policy(obs, mission):
    """A scripted policy whose episode length depends on its outcome: walk ahead until blocked, turn left
    when blocked, pick when the mission's object is in front. Successes end early; every failure is a
    time-out (it never picks anything else), which lasts the whole step limit."""
    view = obs[:, -1]
    v = view.shape[1]
    front = view[:, v - 2, v // 2].astype(np.int64)  # [kind, color, shade, size] of the cell ahead
    goal = np.stack([parse(m) for m in mission]).astype(np.int64)  # (color, type, shade, size)
    is_goal = ((front[:, 0] == KIND_KEY + goal[:, 1]) & (front[:, 1] == goal[:, 0] + 1)
               & (front[:, 2] == goal[:, 2] + 1) & (front[:, 3] == goal[:, 3] + 1))
    blocked = front[:, 0] != KIND_EMPTY
    action = np.where(is_goal, ACTION_PICK, np.where(blocked, ACTION_LEFT, ACTION_FORWARD))
    return np.eye(4, dtype=np.float32)[action]


def first_episode_outcomes(cfg, n_envs, seed):
    """The true outcome distribution, read straight from the world: the first episode of each env."""
    world = BatchedFetchAttr(cfg, n_envs, seed)
    view, mission = world.reset()
    first = np.full(n_envs, -1)
    while (first < 0).any():
        res = world.step(seek_goal_policy(view[:, None], mission).argmax(1))
        first = np.where((first < 0) & (res.outcome >= 0), res.outcome, first)
        view, mission = res.view, res.mission
    return first


def test_evaluation_is_unbiased_when_successes_end_sooner_than_failures():
    cfg = small_world()
    truth = first_episode_outcomes(cfg, 4000, seed=11)
    assert set(np.unique(truth)) == {SUCCESS, TIMEOUT}  # the policy fails only by timing out
    p = float(np.mean(truth == SUCCESS))
    assert 0.1 < p < 0.9
    # Many short evaluations (the periodic evaluation's shape: 64 episodes, fewer envs than episodes)
    # and one long one over the default batch of environments.
    short = [evaluate(seek_goal_policy, cfg, 1, "train", Seeds(s).evaluation_env_seeds(0, 64), n_envs=32)
             for s in range(16)]
    long = evaluate(seek_goal_policy, cfg, 1, "train", Seeds(100).evaluation_env_seeds(0, 512))
    for rates, n in (([r for r, _ in short], 64 * 16), ([long[0]], 512)):
        # Within 3.5 standard errors of the truth (the truth's own error is several times smaller).
        assert abs(np.mean(rates) - p) < 3.5 * (p * (1 - p) / n) ** 0.5, (np.mean(rates), p, n)
    assert all(se == pytest.approx((r * (1 - r) / 64) ** 0.5) for r, se in short)
