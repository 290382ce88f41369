"""The recurrent core (network.core=gru): its loss against a step-by-step numpy reference, the actor's
one-step policy against the learner's unroll, episode starts, padding, and the config's refusals."""
import dataclasses

import numpy as np
import pytest
import torch

from higher_dist.config import ConfigError, NetworkConfig, validate
from higher_dist.config_presets import make_config
from higher_dist.learning.acting import EpisodeCollector, RecurrentQFunction, first_episodes, make_policy, q_values
from higher_dist.learning.networks import weights_numpy
from higher_dist.learning.recurrent import RecurrentQNetwork, q_network, sequence_dqn_terms
from higher_dist.learning.seeds import Seeds

GRU = NetworkConfig(core="gru", frame_stack=1)


def gru_config(preset="her", world="small", **overrides):
    cfg = make_config(preset, world, **overrides)
    return dataclasses.replace(cfg, network=dataclasses.replace(cfg.network, core="gru", frame_stack=1))


def random_views(rng, shape):
    """Valid views: each channel within its range on the paper world's tables."""
    kinds = rng.integers(0, 5, shape)
    rest = [rng.integers(0, hi + 1, shape) for hi in (6, 5, 5)]
    return np.stack([kinds, *rest], axis=-1).astype(np.uint8)


def make_net(seed):
    torch.manual_seed(seed)
    net = RecurrentQNetwork(GRU)
    with torch.no_grad():  # a head far from its near-zero start, so Q-values differ between actions
        for p in (net.value.weight, net.advantage.weight):
            p.normal_(0.0, 0.5)
    return net


def unroll_step_by_step(net, views, mission):
    """Q (B, T, A) computed one step at a time, carrying the state by hand (numpy out)."""
    text = net.encode_mission(mission)
    state, out = None, []
    for t in range(views.shape[1]):
        q, state = net.q_sequence(views[:, t:t + 1], text, state)
        out.append(q[:, 0])
    return torch.stack(out, dim=1).detach().numpy()


def random_episode_batch(rng, b=3, steps=(5, 2, 7), n=3, gamma=0.9):
    t_max = max(steps)
    frames = random_views(rng, (b, t_max + 1, 7, 7))
    action = rng.integers(0, 4, (b, t_max))
    reward = rng.normal(size=(b, t_max)).astype(np.float32)
    discount = np.zeros((b, t_max), np.float32)
    next_step = np.tile(np.arange(t_max), (b, 1))
    mask = np.zeros((b, t_max), np.float32)
    for i, length in enumerate(steps):
        frames[i, length + 1:] = frames[i, length]  # padded with the final frame, as replay pads
        for t in range(length):
            m = min(n, length - t)
            next_step[i, t], discount[i, t], mask[i, t] = t + m, gamma ** m, 1.0
        if i == 0:
            discount[i, length - 1] = 0.0  # a terminal pick ends episode 0
        action[i, length:] = 0
        reward[i, length:] = 0.0
    mission = np.zeros((b, 10), np.int64)
    mission[:, :4] = rng.integers(4, 20, (b, 4))
    weights = rng.uniform(0.2, 1.0, b).astype(np.float32)
    return frames, mission, action, reward, discount, next_step, mask, weights


@pytest.mark.parametrize("double", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_episode_loss_matches_a_step_by_step_numpy_reference(double, seed):
    rng = np.random.default_rng(seed)
    online, target = make_net(seed), make_net(seed + 100)
    frames, mission, action, reward, discount, next_step, mask, weights = random_episode_batch(rng)
    as_t = lambda a: torch.as_tensor(a)  # noqa: E731
    loss, td, q_mean, y_mean = sequence_dqn_terms(
        online, target, as_t(frames), as_t(mission), as_t(action), as_t(reward), as_t(discount),
        as_t(next_step), as_t(mask), as_t(weights), huber_delta=1.0, double=double)

    q_on = unroll_step_by_step(online, as_t(frames), as_t(mission))
    q_tg = unroll_step_by_step(target, as_t(frames), as_t(mission))
    losses, tds, qs, ys = [], np.zeros_like(reward), [], []
    for i in range(frames.shape[0]):
        for t in range(int(mask[i].sum())):
            j = next_step[i, t]
            best = int(np.argmax(q_on[i, j] if double else q_tg[i, j]))
            y = reward[i, t] + discount[i, t] * q_tg[i, j, best]
            q = q_on[i, t, action[i, t]]
            err = abs(y - q)
            losses.append(weights[i] * (0.5 * err ** 2 if err <= 1.0 else err - 0.5))
            tds[i, t] = err
            qs.append(q)
            ys.append(y)
    assert float(loss.detach()) == pytest.approx(np.mean(losses), rel=1e-5, abs=1e-6)
    np.testing.assert_allclose(td.numpy(), tds, rtol=1e-5, atol=1e-6)  # 0 on padding
    assert float(q_mean) == pytest.approx(np.mean(qs), rel=1e-5, abs=1e-6)
    assert float(y_mean) == pytest.approx(np.mean(ys), rel=1e-5, abs=1e-6)


def test_padding_changes_neither_the_loss_nor_the_gradient():
    rng = np.random.default_rng(3)
    online, target = make_net(3), make_net(4)
    batch = random_episode_batch(rng, b=2, steps=(4, 4))
    frames, mission, action, reward, discount, next_step, mask, weights = batch

    def loss_and_grad(frames, action, reward, discount, next_step, mask):
        online.zero_grad()
        args = [torch.as_tensor(a) for a in (frames, mission, action, reward, discount, next_step, mask, weights)]
        loss, td, _, _ = sequence_dqn_terms(online, target, *args)
        loss.backward()
        return float(loss.detach()), td.numpy()[:, :4], online.memory.weight_hh_l0.grad.clone()

    base = loss_and_grad(frames, action, reward, discount, next_step, mask)
    pad = 3  # three more steps of garbage, masked out
    grow = lambda a, v: np.concatenate([a, np.full((a.shape[0], pad) + a.shape[2:], v, a.dtype)], axis=1)  # noqa: E731
    frames_p = np.concatenate([frames, random_views(rng, (2, pad, 7, 7))], axis=1)
    padded = loss_and_grad(frames_p, grow(action, 3), grow(reward, 5.0), grow(discount, 0.9),
                           np.concatenate([next_step, np.tile(np.arange(4, 4 + pad), (2, 1))], axis=1),
                           grow(mask, 0.0))
    assert padded[0] == pytest.approx(base[0], rel=1e-6)
    np.testing.assert_allclose(padded[1], base[1], rtol=1e-6)
    torch.testing.assert_close(padded[2], base[2])


def test_the_actors_one_step_policy_equals_the_learners_unroll():
    """What an actor computes step by step, its state started afresh at each episode's first view (some
    environments start their next episode while others are mid-way), is what the learner computes
    unrolling each episode from its first view: every greedy action taken is the unroll's argmax."""
    torch.set_num_threads(1)
    cfg = gru_config()
    policy = make_policy(cfg.network)
    assert isinstance(policy, RecurrentQFunction)
    learner_net = make_net(5)
    policy.load(weights_numpy(learner_net))
    collector = EpisodeCollector(cfg.world, 6, 1, seed=0)
    episodes = []
    for _ in range(90):
        episodes += collector.step(q_values(policy, collector).argmax(axis=1))
    assert len(episodes) > 6  # some environments finished more than one episode
    for ep in episodes:
        q = learner_net(torch.as_tensor(ep.frames[None, :-1]), torch.as_tensor(ep.mission[None]))[0]
        np.testing.assert_array_equal(q.detach().numpy().argmax(axis=1), ep.actions)


def test_a_fresh_state_at_a_start_and_a_refusal_mid_episode():
    torch.set_num_threads(1)
    policy = make_policy(GRU)
    policy.load(weights_numpy(make_net(6)))
    rng = np.random.default_rng(6)
    obs, mission = random_views(rng, (3, 1, 7, 7)), np.tile(np.array([[5, 6, 7, 8, 0, 0, 0, 0, 0, 0]]), (3, 1))
    first = policy(obs, mission, starts=np.ones(3, bool))
    later = policy(obs, mission, starts=np.array([False, True, False]))
    np.testing.assert_allclose(later[1], first[1], rtol=1e-6)  # env 1 started afresh
    assert not np.allclose(later[0], first[0])  # env 0 remembers its first step
    with pytest.raises(ValueError, match="mid-episode"):
        policy(obs[:2], mission[:2], starts=np.array([True, False]))
    assert policy(obs[:2], mission[:2], starts=np.ones(2, bool)).shape == (2, 4)  # a new batch, all starting


def test_greedy_evaluation_of_a_recurrent_policy_is_repeatable():
    torch.set_num_threads(1)
    cfg = gru_config()
    policy = make_policy(cfg.network)
    policy.load(weights_numpy(make_net(7)))
    seeds = Seeds(0).evaluation_env_seeds(0, 12)
    a = first_episodes(policy, cfg.world, 1, "train", seeds, n_envs=5)
    b = first_episodes(policy, cfg.world, 1, "train", seeds, n_envs=12)  # other batches, same episodes
    assert [ep.actions.tolist() for ep in a] == [ep.actions.tolist() for ep in b]


def test_the_config_refuses_a_recurrent_core_on_a_frame_stack():
    # Asked for alone, the recurrent core comes without a frame stack; with one asked for, it is refused.
    assert make_config("her", "paper", **{"network.core": "gru"}).network.frame_stack == 1
    with pytest.raises(ConfigError, match="network.frame_stack"):
        make_config("her", "paper", **{"network.core": "gru", "network.frame_stack": 4})
    cfg = make_config("her", "small")
    with pytest.raises(ConfigError, match="network.frame_stack"):
        validate(dataclasses.replace(cfg, network=dataclasses.replace(cfg.network, core="gru")))
    with pytest.raises(ConfigError, match="network.core"):
        validate(dataclasses.replace(cfg, network=dataclasses.replace(cfg.network, core="lstm")))
    with pytest.raises(ConfigError, match="dqn.sequence_batch"):
        validate(dataclasses.replace(gru_config(), dqn=dataclasses.replace(cfg.dqn, sequence_batch=0)))
    with pytest.raises(ValueError, match="frame_stack must be 1"):
        RecurrentQNetwork(NetworkConfig(core="gru", frame_stack=4))
    assert isinstance(q_network(GRU), RecurrentQNetwork) and not isinstance(q_network(NetworkConfig()), RecurrentQNetwork)


def test_a_recurrent_agents_cycles_are_judged_on_the_frame_stack_defaults_views():
    from higher_dist.learning.episode_ends import RECURRENT_JUDGED_STACK, judged_stack

    assert judged_stack(1, "gru") == RECURRENT_JUDGED_STACK == NetworkConfig().frame_stack
    assert judged_stack(8, "stack") == 8 and judged_stack(1, "stack") == 1
