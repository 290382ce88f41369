from dataclasses import replace as _replace

import numpy as np
import pytest

from higher_dist.config import ExplorationConfig
from higher_dist.learning.exploration import (Explorer, actor_epsilons, apex_epsilons, epsilon_greedy, linear_epsilon,
                                              zeta_durations)


def test_apex_epsilons_formula():
    eps = apex_epsilons(5, 0.4, 7.0)
    expected = [0.4 ** (1 + 7.0 * i / 4) for i in range(5)]
    np.testing.assert_allclose(eps, expected, rtol=1e-12)
    assert eps[0] == pytest.approx(0.4) and eps[-1] == pytest.approx(0.4 ** 8)
    assert np.all(np.diff(eps) < 0)
    np.testing.assert_array_equal(apex_epsilons(1, 0.3, 7.0), [0.3])
    with pytest.raises(ValueError):
        apex_epsilons(0, 0.4, 7.0)


def test_linear_schedule_endpoints_and_midpoint():
    cfg = ExplorationConfig(kind="linear", eps_start=1.0, eps_end=0.05, decay_frames=1000)
    assert linear_epsilon(0, cfg) == pytest.approx(1.0)
    assert linear_epsilon(500, cfg) == pytest.approx(0.525)
    assert linear_epsilon(1000, cfg) == pytest.approx(0.05)
    assert linear_epsilon(10**9, cfg) == pytest.approx(0.05)


def test_apex_actor_epsilons_spread_the_ladder_over_every_env():
    cfg = ExplorationConfig(kind="apex", eps_base=0.4, apex_alpha=2.0)
    n_actors, n_envs = 3, 4
    per_actor = [actor_epsilons(cfg, a, n_actors, n_envs, frame=0) for a in range(n_actors)]
    ladder = apex_epsilons(n_actors * n_envs, 0.4, 2.0)
    np.testing.assert_allclose(np.sort(np.concatenate(per_actor)), np.sort(ladder))
    for eps in per_actor:
        assert eps.shape == (n_envs,)
        assert len(np.unique(eps)) == n_envs  # one actor explores at several rates
    # Fixed rates: the frame does not matter.
    np.testing.assert_array_equal(actor_epsilons(cfg, 1, n_actors, n_envs, frame=10**7), per_actor[1])
    # A single actor with a single env gets eps_base.
    np.testing.assert_array_equal(actor_epsilons(cfg, 0, 1, 1, frame=0), [0.4])
    with pytest.raises(ValueError):
        actor_epsilons(cfg, 3, n_actors, n_envs, frame=0)


def test_linear_actor_epsilons_share_the_decayed_value():
    cfg = ExplorationConfig(kind="linear", eps_start=1.0, eps_end=0.1, decay_frames=100)
    eps = actor_epsilons(cfg, 1, 2, 5, frame=50)
    np.testing.assert_allclose(eps, np.full(5, 0.55))


def test_epsilon_greedy_zero_is_argmax():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    actions = epsilon_greedy(q, np.zeros(500), rng)
    assert actions.dtype == np.int64
    np.testing.assert_array_equal(actions, q.argmax(axis=1))


def test_epsilon_greedy_one_is_roughly_uniform():
    rng = np.random.default_rng(1)
    n = 40_000
    q = np.tile([0.0, 5.0, 1.0, 2.0], (n, 1))
    counts = np.bincount(epsilon_greedy(q, np.ones(n), rng), minlength=4)
    expected = n / 4
    chi2 = np.sum((counts - expected) ** 2 / expected)
    assert chi2 < 25.0  # 3 degrees of freedom: 0.999 quantile 16.3


def test_epsilon_greedy_per_row_rates():
    rng = np.random.default_rng(2)
    n = 20_000
    q = np.tile([0.0, 0.0, 3.0, 0.0], (n, 1))
    eps = np.where(np.arange(n) < n // 2, 0.2, 0.8)
    actions = epsilon_greedy(q, eps, rng)
    # A random action is the greedy one a quarter of the time: P(non-greedy) = 0.75 * eps.
    low, high = actions[: n // 2], actions[n // 2:]
    assert np.mean(low != 2) == pytest.approx(0.15, abs=0.02)
    assert np.mean(high != 2) == pytest.approx(0.60, abs=0.02)
    # A scalar epsilon broadcasts.
    assert epsilon_greedy(q[:10], 0.0, rng).tolist() == [2] * 10


def test_apex_warmup_starts_every_slot_at_one_and_reaches_the_ladder():
    cfg = _replace(ExplorationConfig(), kind="apex", warmup_frames=1000)
    plain = actor_epsilons(_replace(cfg, warmup_frames=0), 0, 2, 8, 0)
    np.testing.assert_allclose(actor_epsilons(cfg, 0, 2, 8, 0), 1.0)
    np.testing.assert_allclose(actor_epsilons(cfg, 0, 2, 8, 500), (1.0 + plain) / 2)
    np.testing.assert_allclose(actor_epsilons(cfg, 0, 2, 8, 1000), plain)
    np.testing.assert_allclose(actor_epsilons(cfg, 0, 2, 8, 10**7), plain)


def test_explorer_without_repeats_is_plain_epsilon_greedy_draw_for_draw():
    q = np.random.default_rng(1).normal(size=(16, 4))
    eps = np.linspace(0.0, 1.0, 16)
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    explorer = Explorer(16, 4, repeat_max=1)
    for _ in range(20):
        assert np.array_equal(explorer(q, eps, a), epsilon_greedy(q, eps, b))


def test_zeta_durations_follow_a_power_law():
    n, p = zeta_durations(10, 2.0)
    assert list(n) == list(range(1, 11)) and p.sum() == pytest.approx(1.0)
    assert p[0] / p[1] == pytest.approx(4.0) and p[0] / p[9] == pytest.approx(100.0)


def test_explorer_holds_an_exploratory_action_for_zeta_distributed_runs():
    # eps = 1: every step belongs to a run; a run is a maximal stretch of one held action that starts
    # when the previous run's counter reaches zero. Measure run lengths through the counter itself.
    envs, steps = 2000, 40
    explorer = Explorer(envs, 4, repeat_max=8, mu=2.0)
    rng = np.random.default_rng(0)
    q = np.zeros((envs, 4))
    lengths, current = [], np.zeros(envs, np.int64)
    prev_action = None
    for _ in range(steps):
        starting = explorer.left == 0
        lengths.extend(current[starting & (current > 0)])
        current[starting] = 0
        actions = explorer(q, 1.0, rng)
        if prev_action is not None:
            continuing = ~starting
            assert np.array_equal(actions[continuing], prev_action[continuing])
        current += 1
        prev_action = actions
    lengths = np.asarray(lengths)
    _, p = zeta_durations(8, 2.0)
    for d in (1, 2, 3):
        assert np.mean(lengths == d) == pytest.approx(p[d - 1], abs=0.02)
    assert lengths.max() <= 8


def test_explorer_with_zero_epsilon_is_greedy_and_runs_end_with_the_episode():
    q = np.tile(np.array([0.0, 0.0, 1.0, 0.0]), (6, 1))
    explorer = Explorer(6, 4, repeat_max=50, mu=0.5)
    rng = np.random.default_rng(3)
    assert np.array_equal(explorer(q, 0.0, rng), np.full(6, 2))
    explorer(q, 1.0, rng)  # every env starts a run (mu 0.5: most last many steps)
    ended = np.array([True, False, True, False, True, False])
    explorer.episodes_ended(ended)
    assert (explorer.left[ended] == 0).all()
    assert np.array_equal(explorer(q, 0.0, rng)[ended], np.full(3, 2))


def test_explorer_refuses_a_batch_of_the_wrong_size():
    with pytest.raises(ValueError, match="rows"):
        Explorer(4, 4, repeat_max=3)(np.zeros((5, 4)), 0.5, np.random.default_rng(0))
