"""The acting loop: episodes assembled from batched steps, frame stacks, and evaluation goal sets."""
import numpy as np
import pytest
import torch

from higher_dist.config import make_config, small_world
from higher_dist.learning.acting import EpisodeCollector, TorchQFunction, evaluate
from higher_dist.learning.dqn import DQNLearner
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK
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
    q.load(DQNLearner(cfg.network, cfg.dqn).weights_numpy())
    rate = evaluate(q, cfg.world, cfg.network.frame_stack, 20, "heldout", seed=0, n_envs=8)
    assert 0.0 <= rate <= 1.0
    assert rate == evaluate(q, cfg.world, cfg.network.frame_stack, 20, "heldout", seed=0, n_envs=8)
