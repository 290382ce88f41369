"""DQNUpdater's update: priorities, target schedule, gradient clipping, non-finite batches, checkpoints,
published weights, the compiled and joint paths, the averaged weights and the learning-rate schedule."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from higher_dist.config import ConfigError, DQNConfig, NetworkConfig, from_dict
from higher_dist.learning.dqn import DQNUpdater, dqn_loss, learning_rate_at
from higher_dist.learning.networks import QNetwork, load_weights_numpy
from higher_dist.world.spec import DEFAULT_SPEC
from support.dqn_batches import SMALL, batch_tensors, needs_cxx, random_batch

torch.set_num_threads(1)


def make_learner(**dqn_overrides) -> DQNUpdater:
    # Eager unless a test asks: a background compile would switch paths in the middle of a test.
    return DQNUpdater(SMALL, DQNConfig(**{"compile": False, **dqn_overrides}), seed=0)


def params_of(net: nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in net.parameters()]


def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b))


def test_a_target_update_outside_its_choices_is_refused_by_the_config_naming_the_field() -> None:
    from higher_dist.config import Config

    data = Config().to_dict()
    data["dqn"]["target_update"] = "soft"
    with pytest.raises(ConfigError, match=r"dqn.target_update: must be one of period, polyak, got 'soft'"):
        from_dict(data)


def test_update_returns_priorities_of_the_pre_update_networks() -> None:
    learner = make_learner()
    batch = random_batch(np.random.default_rng(1), 16)
    _, expected, _ = dqn_loss(copy.deepcopy(learner.online), copy.deepcopy(learner.target),
                              **batch_tensors(batch))
    before = params_of(learner.online)
    priorities, metrics = learner.update(batch)
    assert isinstance(priorities, np.ndarray) and priorities.shape == (16,) and priorities.dtype == np.float32
    np.testing.assert_allclose(priorities, expected.numpy(), rtol=1e-5, atol=1e-6)
    assert {"loss", "q_mean", "td_abs_mean", "target_mean", "grad_norm"} <= set(metrics)
    assert learner.updates == 1 and not same(before, params_of(learner.online))


def test_period_target_update_copies_exactly_at_the_period() -> None:
    learner = make_learner(target_update="period", target_period=3)
    rng = np.random.default_rng(2)
    initial = params_of(learner.target)
    assert same(initial, params_of(learner.online))
    for _ in range(2):
        learner.update(random_batch(rng, 8))
        assert same(initial, params_of(learner.target))
        assert not same(initial, params_of(learner.online))
    learner.update(random_batch(rng, 8))  # update 3: copy
    at_copy = params_of(learner.online)
    assert same(at_copy, params_of(learner.target))
    learner.update(random_batch(rng, 8))  # update 4: the target holds the copy of update 3
    assert same(at_copy, params_of(learner.target))
    assert not same(at_copy, params_of(learner.online))


def test_polyak_target_moves_by_tau() -> None:
    tau = 0.1
    learner = make_learner(target_update="polyak", polyak_tau=tau)
    rng = np.random.default_rng(3)
    for _ in range(3):
        target_before = params_of(learner.target)
        learner.update(random_batch(rng, 8))
        online_after = params_of(learner.online)
        for t_before, o_after, t_after in zip(target_before, online_after, params_of(learner.target)):
            assert torch.allclose(t_after, t_before + tau * (o_after - t_before), atol=1e-7)


def test_gradients_are_clipped_to_the_configured_norm() -> None:
    learner = make_learner(grad_clip=1e-3)
    _, metrics = learner.update(random_batch(np.random.default_rng(4), 16))
    clipped = torch.sqrt(sum(p.grad.square().sum() for p in learner.online.parameters()))
    assert metrics["grad_norm"] > 1e-3
    assert clipped.item() == pytest.approx(1e-3, rel=1e-3)


def test_non_finite_batch_is_skipped_without_touching_the_weights() -> None:
    learner = make_learner()
    batch = random_batch(np.random.default_rng(8), 8)
    batch.reward[0] = np.nan
    before = params_of(learner.online)
    _, metrics = learner.update(batch)
    assert not np.isfinite(metrics["grad_norm"]) and metrics["skipped_updates"] == 1.0
    assert same(before, params_of(learner.online))
    assert all(torch.isfinite(p).all() for p in learner.online.parameters())
    batch.reward[0] = 0.0
    learner.update(batch)  # the next good batch steps as usual
    assert not same(before, params_of(learner.online))


def test_learner_reduces_loss_on_a_fixed_batch() -> None:
    # A target that never moves turns the updates into a regression the learner must fit.
    learner = make_learner(lr=2e-3, target_period=10 ** 9)
    batch = random_batch(np.random.default_rng(5), 32)
    losses = [learner.update(batch)[1]["loss"] for _ in range(50)]
    assert np.mean(losses[-5:]) < 0.3 * losses[0]


def test_state_dict_resumes_exactly() -> None:
    rng = np.random.default_rng(6)
    batches = [random_batch(rng, 8) for _ in range(4)]
    a = make_learner(target_period=2)
    for batch in batches[:3]:
        a.update(batch)
    state = copy.deepcopy(a.state_dict())
    b = DQNUpdater(SMALL, DQNConfig(target_period=2, compile=False), seed=123)
    b.load_state_dict(state)
    assert b.updates == 3
    prio_a, _ = a.update(batches[3])
    prio_b, _ = b.update(batches[3])  # update 4 also copies the target: both must do it
    np.testing.assert_array_equal(prio_a, prio_b)
    assert same(params_of(a.online), params_of(b.online))
    assert same(params_of(a.target), params_of(b.target))


def test_published_weights_reproduce_the_learners_q_values() -> None:
    learner = make_learner()
    rng = np.random.default_rng(7)
    learner.update(random_batch(rng, 8))
    batch = random_batch(rng, 5)
    actor_net = QNetwork(SMALL)
    load_weights_numpy(actor_net, learner.weights_numpy())
    with torch.no_grad():
        q_actor = actor_net(torch.from_numpy(batch.obs), torch.from_numpy(batch.mission)).numpy()
    with torch.no_grad():
        q_learner = learner.online(torch.from_numpy(batch.obs), torch.from_numpy(batch.mission)).numpy()
    assert q_learner.shape == (5, DEFAULT_SPEC.n_actions)
    np.testing.assert_array_equal(q_actor, q_learner)
    # Loading into the learner sets both networks.
    other = DQNUpdater(SMALL, DQNConfig(compile=False), seed=99)
    other.load_weights_numpy(learner.weights_numpy())
    assert same(params_of(other.online), params_of(learner.online))
    assert same(params_of(other.target), params_of(learner.online))


def test_joint_online_forward_equals_separate_forwards_on_a_real_network() -> None:
    """One online forward over obs and next_obs stacked: same loss, priorities and gradients."""
    torch.manual_seed(0)
    online, target = QNetwork(SMALL), QNetwork(SMALL)
    tensors = batch_tensors(random_batch(np.random.default_rng(9), 11))
    results = []
    for joint in (False, True):
        online.zero_grad()
        loss, prio, _ = dqn_loss(online, target, **tensors, joint_online=joint)
        loss.backward()
        results.append((loss.detach(), prio, [p.grad.clone() for p in online.parameters()]))
    (loss_a, prio_a, grads_a), (loss_b, prio_b, grads_b) = results
    assert torch.allclose(loss_a, loss_b, atol=1e-6) and torch.allclose(prio_a, prio_b, atol=1e-6)
    for g_a, g_b in zip(grads_a, grads_b):
        assert torch.allclose(g_a, g_b, atol=1e-6)


@needs_cxx
@pytest.mark.parametrize("text", ["gru", "bow"])
def test_compiled_and_eager_learners_agree_update_by_update(text: str) -> None:
    """The compiled loss (inductor) steps the same as eager: same priorities, metrics and weights after
    several updates, within float round-off (the compiler may reorder sums), with either instruction
    encoder."""
    rng = np.random.default_rng(10)
    batches = [random_batch(rng, 16) for _ in range(4)]
    net = NetworkConfig(**{**SMALL.__dict__, "text": text})
    eager = DQNUpdater(net, DQNConfig(compile=False, target_period=2), seed=0)
    compiled = DQNUpdater(net, DQNConfig(compile=True, target_period=2), seed=0)
    compiled.compiled.start(compiled._tensors(batches[0]), background=False)
    assert compiled.compiled.ready, compiled.compiled.failed
    for batch in batches:
        prio_e, metrics_e = eager.update(batch)
        prio_c, metrics_c = compiled.update(batch)
        np.testing.assert_allclose(prio_c, prio_e, rtol=1e-4, atol=1e-5)
        for key in ("loss", "q_mean", "td_abs_mean", "target_mean", "grad_norm"):
            assert metrics_c[key] == pytest.approx(metrics_e[key], rel=1e-4, abs=1e-6), key
    for p_e, p_c in zip(params_of(eager.online), params_of(compiled.online)):
        assert torch.allclose(p_e, p_c, rtol=1e-4, atol=1e-5)
    # The compiled graph refuses nothing by itself: the learner still checks the views first.
    bad = random_batch(rng, 16)
    bad.obs[0, 0, 0, 0, 0] = 9
    with pytest.raises(ValueError, match="out of range"):
        compiled.update(bad)


def test_a_failed_compile_leaves_the_learner_eager() -> None:
    learner = make_learner(compile=True)
    batch = random_batch(np.random.default_rng(11), 8)
    tensors = learner._tensors(batch)
    tensors["obs"] = tensors["obs"][:, :1]  # a frame stack the network cannot take: tracing raises
    learner.compiled.start(tensors, background=False)
    assert not learner.compiled.ready and "expected" in learner.compiled.failed
    prio, metrics = learner.update(batch)  # the eager path, as if compile were off
    assert prio.shape == (8,) and np.isfinite(metrics["loss"])


def test_averaged_weights_follow_the_moving_average_and_never_touch_learning() -> None:
    """dqn.average_tau: avg <- avg + tau (online - avg) after each update, checked in numpy; the online
    and target networks step exactly as without it, and a checkpoint carries the average."""
    tau = 0.2
    rng = np.random.default_rng(11)
    batches = [random_batch(rng, 8) for _ in range(4)]
    plain, averaged = make_learner(target_period=2, average_tau=0.0), make_learner(target_period=2, average_tau=tau)
    assert plain.average_weights_numpy() is None
    expected = {k: v.copy() for k, v in averaged.weights_numpy().items()}  # starts at the online weights
    for batch in batches[:3]:
        prio_plain, _ = plain.update(batch)
        prio_avg, _ = averaged.update(batch)
        np.testing.assert_array_equal(prio_plain, prio_avg)
        online = averaged.weights_numpy()
        expected = {k: v + tau * (online[k] - v) for k, v in expected.items()}
        got = averaged.average_weights_numpy()
        assert got.keys() == expected.keys()
        for k in expected:
            np.testing.assert_allclose(got[k], expected[k], rtol=1e-5, atol=1e-6)
    assert same(params_of(plain.online), params_of(averaged.online))
    assert same(params_of(plain.target), params_of(averaged.target))
    assert not same(params_of(averaged.average), params_of(averaged.online))
    resumed = make_learner(target_period=2, average_tau=tau)
    resumed.load_state_dict(copy.deepcopy(averaged.state_dict()))
    assert same(params_of(resumed.average), params_of(averaged.average))
    averaged.update(batches[3])
    resumed.update(batches[3])
    assert same(params_of(resumed.average), params_of(averaged.average))
    # A checkpoint written without the average starts it from the online weights.
    late = make_learner(average_tau=tau)
    late.load_state_dict(copy.deepcopy(plain.state_dict()))
    assert same(params_of(late.average), params_of(plain.online))


@pytest.mark.parametrize("frames, expected", [(0, 1e-3), (500, 0.775e-3), (1000, 0.55e-3), (1500, 0.325e-3),
                                              (2000, 1e-4), (10 ** 6, 1e-4), (-5, 1e-3)])
def test_learning_rate_falls_linearly_to_its_end_fraction_then_stays(frames, expected) -> None:
    cfg = DQNConfig(lr=1e-3, lr_decay_frames=2000, lr_end_fraction=0.1)
    assert learning_rate_at(cfg, frames) == pytest.approx(expected, rel=1e-9)
    assert learning_rate_at(DQNConfig(lr=1e-3, lr_decay_frames=0), frames) == 1e-3  # 0 decay frames: constant


def test_the_learner_steps_with_the_scheduled_learning_rate() -> None:
    """The optimiser's lr follows the learner's frame count (original episodes only), update by update."""
    from higher_dist.config_presets import make_config
    from higher_dist.learning.acting import EpisodeCollector
    from higher_dist.learning.learner import Learner

    cfg = make_config("dqn", "small", **{"replay.min_size": 100, "dqn.batch_size": 16, "dqn.lr": 1e-3,
                                         "dqn.lr_decay_frames": 600, "dqn.lr_end_fraction": 0.2})
    core = Learner(cfg)
    collector = EpisodeCollector(cfg.world, 8, cfg.network.frame_stack, seed=3)
    rng = np.random.default_rng(3)
    seen = []
    while core.frames < 900:
        core.add_episodes(collector.step(rng.integers(0, 4, size=8)))
        if core.train_available(max_updates=5):
            seen.append((core.frames, core.dqn.learning_rate, core.metrics()["learning_rate"]))
    assert len(seen) > 5
    for frames, lr, reported in seen:
        assert lr == pytest.approx(learning_rate_at(cfg.dqn, frames)) and reported == lr
    assert seen[0][1] > seen[-1][1] == pytest.approx(2e-4)
