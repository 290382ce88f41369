"""dqn_loss against a numpy reference on hand-made and random batches, and the shared mission encoding
(DQNUpdater's update is tested in test_dqn_learner.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from higher_dist.learning.compiled_loss import CompiledLoss
from higher_dist.learning.dqn import DQNUpdater, dqn_loss, dqn_terms
from higher_dist.learning.networks import QNetwork
from support.dqn_batches import GAMMA, SMALL, batch_tensors, needs_cxx, random_batch

torch.set_num_threads(1)



class TableQ(nn.Module):
    """A fake Q-function: the Q-values of sample b are row `obs[b, 0, 0, 0, 0]` of a learnable table,
    so a test fixes every Q-value and reads the gradient per (row, action)."""

    def __init__(self, table: np.ndarray):
        super().__init__()
        self.table = nn.Parameter(torch.tensor(table, dtype=torch.float32))

    def forward(self, obs: torch.Tensor, mission: torch.Tensor) -> torch.Tensor:
        return self.q_values(obs, self.encode_mission(mission))

    def encode_mission(self, mission: torch.Tensor) -> torch.Tensor:  # QNetwork's interface: no text here
        return mission

    def q_values(self, obs: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        return self.table[obs[:, 0, 0, 0, 0].long()]


def ids_as_obs(ids: np.ndarray) -> torch.Tensor:
    obs = torch.zeros(len(ids), 1, 7, 7, 4, dtype=torch.uint8)
    obs[:, 0, 0, 0, 0] = torch.from_numpy(ids.astype(np.uint8))
    return obs


def reference(q_on, q_tg, action, reward, discount, weights, delta, double):
    """numpy: rows 0..B-1 of the tables are obs, rows B..2B-1 next_obs."""
    b = len(action)
    rows = np.arange(b)
    q = q_on[rows, action]
    chooser = q_on[b:] if double else q_tg[b:]
    y = reward + discount * q_tg[b:][rows, chooser.argmax(axis=1)]
    td = y - q
    huber = np.where(np.abs(td) <= delta, 0.5 * td ** 2, delta * (np.abs(td) - 0.5 * delta))
    grad = np.zeros_like(q_on)
    grad[rows, action] = weights * np.clip(q - y, -delta, delta) / b
    return (weights * huber).mean(), np.abs(td), y, grad


def run_loss(q_on, q_tg, action, reward, discount, weights, delta=1.0, double=True, path="separate"):
    """path: "separate" online forwards, one "joint" forward over obs and next_obs, or "compiled"
    (torch.compile of the same terms)."""
    b = len(action)
    online, target = TableQ(q_on), TableQ(q_tg)
    batch = dict(obs=ids_as_obs(np.arange(b)), mission=torch.zeros(b, 10, dtype=torch.long),
                 action=torch.tensor(action), reward=torch.tensor(reward, dtype=torch.float32),
                 discount=torch.tensor(discount, dtype=torch.float32), next_obs=ids_as_obs(np.arange(b) + b),
                 weights=torch.tensor(weights, dtype=torch.float32))
    if path == "compiled":
        compiled = CompiledLoss(dqn_terms, online, target, huber_delta=delta, double=double, joint_online=False)
        compiled.start(batch, background=False)
        assert compiled.ready, compiled.failed
        loss, prio, q_mean, y_mean = compiled(batch)
        metrics = {"loss": loss.item(), "q_mean": q_mean.item(), "td_abs_mean": prio.mean().item(),
                   "target_mean": y_mean.item()}
    else:
        loss, prio, metrics = dqn_loss(online, target, **batch, huber_delta=delta, double=double,
                                       joint_online=path == "joint")
    loss.backward()
    return loss, prio, metrics, online, target


PATHS = ["separate", "joint", pytest.param("compiled", marks=needs_cxx)]


# A hand-made batch of 6 n-step (n=3) transitions, reward/discount as the replay forms them.
Q_ONLINE = np.array([
    [0.1, 0.5, 0.2, 0.0], [0.3, 0.3, 0.9, 0.1], [0.0, 0.2, 0.4, 0.6],
    [0.2, 0.1, 0.0, 0.3], [0.5, 0.5, 0.5, 0.5], [3.0, 0.0, 0.0, 0.0],
    # next_obs rows: online argmax 1, 0, 3, 2, 0, 1
    [0.0, 0.9, 0.1, 0.2], [0.8, 0.1, 0.2, 0.7], [0.1, 0.2, 0.3, 0.9],
    [0.1, 0.2, 9.0, 0.0], [0.4, 0.3, 0.2, 0.1], [0.0, 0.2, 0.1, 0.0],
])
Q_TARGET = np.array([
    [0.0] * 4, [0.0] * 4, [0.0] * 4, [0.0] * 4, [0.0] * 4, [0.0] * 4,
    # next_obs rows: target argmax 3, 0, 1, 2, 0, 1 -> differs from online in rows 0 and 2
    [0.2, 0.4, 0.0, 0.8], [0.6, 0.5, 0.1, 0.0], [0.3, 0.7, 0.2, 0.5],
    [0.0, 0.0, 50.0, 0.0], [0.2, 0.1, 0.0, 0.0], [0.0, 0.3, 0.0, 0.0],
])
ACTION = np.array([1, 2, 3, 3, 0, 0])
REWARD = np.array([0.0, GAMMA * 1.0, 0.0, 0.0, 5.0, 0.0])  # row 1: success on the window's 2nd step
DISCOUNT = np.array([
    GAMMA ** 3,  # 0: full 3-step window, bootstraps from step 3
    0.0,         # 1: the pick ended the episode inside the window: terminal
    GAMMA ** 2,  # 2: time-out after 2 steps: truncated, still bootstraps (gamma^m with m=2)
    0.0,         # 3: wrong pick: terminal, the huge next Q must not leak in
    GAMMA ** 3,  # 4: big positive TD error: Huber's linear part
    GAMMA ** 3,  # 5: big negative TD error
])
WEIGHTS = np.array([1.0, 0.5, 0.25, 1.0, 0.8, 0.3])


@pytest.mark.parametrize("double,delta,path", [
    (double, delta, path) for double in (True, False) for delta in (1.0, 0.5) for path in ("separate", "joint")
] + [(True, 1.0, PATHS[2])])
def test_loss_priorities_metrics_and_gradient_match_numpy(double: bool, delta: float, path: str) -> None:
    loss, prio, metrics, online, target = run_loss(Q_ONLINE, Q_TARGET, ACTION, REWARD, DISCOUNT, WEIGHTS,
                                                   delta, double, path)
    ref_loss, ref_prio, ref_y, ref_grad = reference(Q_ONLINE, Q_TARGET, ACTION, REWARD, DISCOUNT, WEIGHTS,
                                                    delta, double)
    assert loss.ndim == 0
    assert loss.item() == pytest.approx(ref_loss, rel=1e-5)
    np.testing.assert_allclose(prio.numpy(), ref_prio, rtol=1e-5, atol=1e-6)
    assert not prio.requires_grad and prio.shape == (6,)
    # d loss / d Q_online = Huber'(q - y) * w / B at the taken action, zero elsewhere, and nothing
    # flows through the bootstrap (next_obs rows) or into the target network.
    np.testing.assert_allclose(online.table.grad.numpy(), ref_grad, rtol=1e-5, atol=1e-7)
    assert target.table.grad is None
    q_taken = Q_ONLINE[np.arange(6), ACTION]
    assert metrics["loss"] == pytest.approx(ref_loss, rel=1e-5)
    assert metrics["q_mean"] == pytest.approx(q_taken.mean(), rel=1e-5)
    assert metrics["td_abs_mean"] == pytest.approx(ref_prio.mean(), rel=1e-5)
    assert metrics["target_mean"] == pytest.approx(ref_y.mean(), rel=1e-5)
    assert all(isinstance(v, float) for v in metrics.values())


def test_hand_computed_targets() -> None:
    """The n-step target of each row, written out by hand."""
    _, prio, _, _, _ = run_loss(Q_ONLINE, Q_TARGET, ACTION, REWARD, DISCOUNT, WEIGHTS, double=True)
    q = Q_ONLINE[np.arange(6), ACTION]
    expected_y = np.array([
        GAMMA ** 3 * 0.4,  # a* = 1 by the online net, valued 0.4 by the target (target's own max: 0.8)
        GAMMA,             # terminal: reward only
        GAMMA ** 2 * 0.5,  # truncated: bootstraps with gamma^2 from a* = 3
        0.0,               # terminal: next Q of 50 ignored
        5.0 + GAMMA ** 3 * 0.2,
        GAMMA ** 3 * 0.3,
    ])
    np.testing.assert_allclose(prio.numpy(), np.abs(expected_y - q), rtol=1e-5)


def test_double_and_vanilla_targets_differ_only_where_the_argmax_does() -> None:
    _, prio_double, _, _, _ = run_loss(Q_ONLINE, Q_TARGET, ACTION, REWARD, DISCOUNT, WEIGHTS, double=True)
    _, prio_vanilla, _, _, _ = run_loss(Q_ONLINE, Q_TARGET, ACTION, REWARD, DISCOUNT, WEIGHTS, double=False)
    differs = ~np.isclose(prio_double.numpy(), prio_vanilla.numpy())
    np.testing.assert_array_equal(differs, [True, False, True, False, False, False])
    # Vanilla bootstraps from the target's own max: 0.8 in row 0, 0.7 in row 2 (double: 0.4, 0.5).
    q = Q_ONLINE[np.arange(6), ACTION]
    np.testing.assert_allclose(prio_vanilla.numpy()[[0, 2]],
                               np.abs(np.array([GAMMA ** 3 * 0.8, GAMMA ** 2 * 0.7]) - q[[0, 2]]), rtol=1e-5)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), double=st.booleans(), delta=st.sampled_from([0.3, 1.0, 2.0]),
       joint=st.booleans())
def test_random_batches_match_numpy(seed: int, double: bool, delta: float, joint: bool) -> None:
    rng = np.random.default_rng(seed)
    b = int(rng.integers(1, 20))
    q_on, q_tg = rng.normal(0, 2, (2 * b, 4)), rng.normal(0, 2, (2 * b, 4))
    action = rng.integers(0, 4, b)
    reward = rng.normal(0, 1, b)
    discount = np.where(rng.random(b) < 0.3, 0.0, GAMMA ** rng.integers(1, 4, b))
    weights = rng.uniform(0.1, 1.0, b)
    loss, prio, _, online, _ = run_loss(q_on, q_tg, action, reward, discount, weights, delta, double,
                                        "joint" if joint else "separate")
    ref_loss, ref_prio, _, ref_grad = reference(q_on.astype(np.float32), q_tg.astype(np.float32), action,
                                                reward, discount, weights, delta, double)
    assert loss.item() == pytest.approx(ref_loss, rel=1e-4, abs=1e-6)
    np.testing.assert_allclose(prio.numpy(), ref_prio, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(online.table.grad.numpy(), ref_grad, rtol=1e-4, atol=1e-6)


# -- with real networks -------------------------------------------------------------------------


def plain_forward_loss(online: QNetwork, target: QNetwork, obs, mission, action, reward, discount, next_obs,
                       weights, huber_delta: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The double-DQN loss written out with full forwards, the mission encoded once per call."""
    q = online(obs, mission).gather(1, action.view(-1, 1)).squeeze(1)
    with torch.no_grad():
        best = online(next_obs, mission).argmax(dim=1, keepdim=True)
        y = reward + discount * target(next_obs, mission).gather(1, best).squeeze(1)
    loss = (weights * torch.nn.functional.huber_loss(q, y, reduction="none", delta=huber_delta)).mean()
    return loss, (y - q).detach().abs()


def test_shared_mission_encoding_equals_full_forwards() -> None:
    torch.manual_seed(0)
    online, target = QNetwork(SMALL), QNetwork(SMALL)
    tensors = batch_tensors(random_batch(np.random.default_rng(0), 9))
    loss_fast, prio_fast, _ = dqn_loss(online, target, **tensors)
    loss_fast.backward()
    grads_fast = [p.grad.clone() for p in online.parameters()]
    online.zero_grad()
    loss_plain, prio_plain = plain_forward_loss(online, target, **tensors)
    loss_plain.backward()
    assert torch.allclose(loss_fast, loss_plain, atol=1e-6)
    assert torch.allclose(prio_fast, prio_plain, atol=1e-6)
    for g_fast, p in zip(grads_fast, online.parameters()):
        assert torch.allclose(g_fast, p.grad, atol=1e-6)
