"""learning/episode_ends and higher_dist.tally: how episodes end, cycles found exactly, on hand-made frames and the real worlds."""
from __future__ import annotations

import numpy as np
import pytest

from higher_dist import tally
from higher_dist.learning import episode_ends as ends
from higher_dist.config_presets import make_config
from higher_dist.learning.episode import Episode
from higher_dist.world import babyai_language, language
from higher_dist.world.language import encode
from higher_dist.world.spec import ACTION_FORWARD, ACTION_LEFT, SUCCESS, TIMEOUT, WRONG_PICK, WorldSpec


def views(codes) -> np.ndarray:
    """(T, 7, 7, 4) views, view t filled with codes[t]: equal codes, equal views."""
    return np.stack([np.full((7, 7, 4), c, np.uint8) for c in codes])


def test_a_cycle_is_found_at_its_shortest_period_and_the_last_unacted_view_is_ignored():
    rng = np.random.default_rng(0)
    start = list(rng.permutation(50)[:10] + 100)  # distinct views: a search
    assert ends.cycle_period(views(start + [7]), stack=4) == 0
    assert ends.cycle_period(views(start + [1, 2, 3, 4] * 3 + [9]), stack=4) == 4  # a turn on the spot
    assert ends.cycle_period(views(start + [5] * 6 + [9]), stack=4) == 1  # a step into a wall, again and again
    assert ends.cycle_period(views(start + [1, 2] * 5 + [9]), stack=4) == 2  # periodic at 2 and at 4: 2
    # The frame after the last action was never acted on: its equal to an earlier view is no cycle.
    assert ends.cycle_period(views(start + [start[-1]]), stack=1) == 0


def test_a_cycle_needs_the_whole_stack_to_repeat():
    # The last view equals the one 4 steps before, but the views before it differ: with a 4-frame stack
    # the input did not repeat (the agent may be walking a loop it has not closed), with 1 frame it did.
    codes = [10, 11, 12, 13, 1, 20, 21, 22, 1, 9]
    assert ends.cycle_period(views(codes), stack=4) == 0
    assert ends.cycle_period(views(codes), stack=1) == 4


def test_too_short_an_episode_has_no_cycle_and_the_longest_period_is_bounded():
    assert ends.cycle_period(views([1, 1, 1]), stack=4) == 0  # two acted views: no 4-frame input repeated
    long_loop = list(range(40, 40 + ends.MAX_PERIOD + 1)) * 3 + [0]  # period MAX_PERIOD + 1
    assert ends.cycle_period(views(long_loop), stack=1) == 0
    assert ends.cycle_period(views(long_loop), stack=1, max_period=ends.MAX_PERIOD + 1) == ends.MAX_PERIOD + 1


def _episode(codes, outcome, pick_step=-1) -> Episode:
    frames = views(codes)
    n = len(codes) - 1
    return Episode(frames=frames, actions=np.zeros(n, np.uint8), rewards=np.zeros(n, np.float32),
                   mission=encode("fetch a red tiny light key"), outcome=outcome,
                   picked=np.full(4, -1 if pick_step < 0 else 0, np.int8), goal=np.zeros(4, np.int8),
                   pick_step=pick_step)


def test_each_episode_gets_one_kind():
    stack = 4
    assert ends.classify(_episode([1, 2, 3, 4] * 4 + [0], SUCCESS, pick_step=15), stack) == "success"
    # A wrong pick is a wrong outcome even when its views cycled before it.
    assert ends.classify(_episode([1, 2, 3, 4] * 4 + [0], WRONG_PICK, pick_step=15), stack) == "wrong outcome"
    assert ends.classify(_episode([1, 2, 3, 4] * 4 + [0], TIMEOUT), stack) == "cycling"
    assert ends.classify(_episode(list(range(20)), TIMEOUT), stack) == "searching"


def _fixed_action(action: int, n_actions: int):
    def policy(obs, mission):
        q = np.zeros((len(obs), n_actions), np.float32)
        q[:, action] = 1.0
        return q
    return policy


@pytest.mark.parametrize("world", ["paper", "BabyAI-PickupLoc-v0"])
def test_an_agent_turning_on_the_spot_cycles_every_episode_at_period_four(world):
    cfg = make_config("her", world)
    spec = WorldSpec.of(cfg.world)
    episodes = tally.play(cfg, _fixed_action(ACTION_LEFT, spec.n_actions), 12, frames=1000)  # minigrid's left is 0 too
    table = tally.Tally.of(spec, episodes, cfg.network.frame_stack)
    assert len(episodes) == 12 and all(ep.length == spec.max_steps for ep in episodes)
    assert table.total() == {"success": 0, "wrong outcome": 0, "cycling": 12, "searching": 0}
    assert table.periods == {4: 12}
    groups = set(table.groups)
    if spec.family == "babyai":  # a row per location phrase the missions name, or none
        assert groups <= set(babyai_language.LOC_PHRASES) | {"none"} and len(groups) >= 2
        assert "| every mission | 12 | 0.0% | 0.0% | 100.0% | 0.0% |" in table.markdown()
    else:  # a row per mission prefix
        assert groups <= set(language.PREFIXES) and len(groups) >= 2
        assert "| every mission | 12 | 0.0% | 0.0% | 100.0% | 0.0% |" in table.markdown()


def test_walking_straight_ends_against_a_wall_in_a_cycle_of_one_step():
    cfg = make_config("her", "paper")
    spec = WorldSpec.of(cfg.world)
    episodes = tally.play(cfg, _fixed_action(ACTION_FORWARD, spec.n_actions), 16, frames=1000)
    kinds = [ends.classify(ep, cfg.network.frame_stack) for ep in episodes]
    # 40 steps in a 10x10 room: every walk meets a wall or an object and stays there.
    assert kinds == ["cycling"] * 16
    assert {ends.cycle_period(ep.frames, cfg.network.frame_stack) for ep in episodes} == {1}


def test_the_episodes_are_the_runs_evaluation_goals_and_epsilon_breaks_the_cycles():
    cfg = make_config("her", "paper")
    spec = WorldSpec.of(cfg.world)
    turn = _fixed_action(ACTION_LEFT, spec.n_actions)
    a = tally.play(cfg, turn, 8, frames=5000)
    b = tally.play(cfg, turn, 8, frames=5000)
    c = tally.play(cfg, turn, 8, frames=6000)
    assert all(np.array_equal(x.mission, y.mission) and np.array_equal(x.frames[0], y.frames[0]) for x, y in zip(a, b))
    assert any(not np.array_equal(x.frames[0], z.frames[0]) for x, z in zip(a, c))  # fresh goals at another count
    noisy = tally.play(cfg, turn, 32, frames=5000, epsilon=1.0)  # every action random
    assert sum(ends.classify(ep, cfg.network.frame_stack) != "cycling" for ep in noisy) > 16


def _hashed_policy(n_actions: int):
    """Deterministic in its input (as a greedy policy is) but otherwise arbitrary: some episodes cycle,
    some wander, a few pick."""
    def policy(obs, mission):
        return np.stack([np.random.default_rng(abs(hash(o.tobytes() + m.tobytes())) % 2**32).random(n_actions)
                         for o, m in zip(obs, mission)]).astype(np.float32)
    return policy


def test_the_evaluation_reports_the_share_of_episodes_that_cycled_beside_success():
    from higher_dist import metrics as m
    from higher_dist.learning.acting import evaluate_goal_sets, first_episodes

    cfg = make_config("her", "paper")
    spec = WorldSpec.of(cfg.world)
    seeds = list(range(100, 164))
    out = evaluate_goal_sets(_fixed_action(ACTION_LEFT, spec.n_actions), cfg, seeds, suffix=m.AVERAGED_SUFFIX)
    assert out[m.CYCLING_EVAL_TRAIN_AVERAGED] == 1.0 and out[m.CYCLING_EVAL_HELDOUT_AVERAGED] == 1.0
    assert out[m.SUCCESS_EVAL_TRAIN_AVERAGED] == 0.0

    policy = _hashed_policy(spec.n_actions)
    out = evaluate_goal_sets(policy, cfg, seeds)
    kinds = [ends.classify(ep, cfg.network.frame_stack) for ep in first_episodes(policy, cfg.world, 4, "train", seeds)]
    assert out[m.CYCLING_EVAL_TRAIN] == round(kinds.count("cycling") / 64, 4)
    assert out[m.SUCCESS_EVAL_TRAIN] == round(kinds.count("success") / 64, 4)
    assert 0 < out[m.CYCLING_EVAL_TRAIN] < 1  # the policy both cycles and does not: the share is counted, not fixed
