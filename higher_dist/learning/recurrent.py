"""The recurrent core (`network.core=gru`): one view per step into a GRU that runs over the whole episode,
and the double-DQN loss over whole episodes that trains it.

A frame stack shows the policy its last k views and no more, so a greedy policy whose last k views
repeat repeats itself until the time-out (docs/decisions.md, "Where the greedy agent fails"). A GRU's
state can carry anything seen since the episode began. Episodes here are short (40 steps on the paper
world, at most a few hundred on BabyAI), so replay hands the learner whole episodes and every step's
Q-value comes from a state unrolled from the episode's first view: no stored states go stale and no
burn-in is needed (R2D2's two remedies for starting mid-sequence). Actors keep a state per environment
and start it at zero with each episode, as the learner does.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from higher_dist.config import NetworkConfig
from higher_dist.learning.networks import QNetwork
from higher_dist.world.spec import DEFAULT_SPEC, WorldSpec

__all__ = ["RecurrentQNetwork", "q_network", "sequence_dqn_terms"]


class RecurrentQNetwork(QNetwork):
    """The Q-network's view and instruction encoders and head with a GRU (cfg.hidden wide) between the
    fused features and the head. The head reads features + GRU output: at the start, with the GRU's
    output small, the network acts on the current view as a one-frame network would, and the GRU adds
    what it learns to remember."""

    def __init__(self, cfg: NetworkConfig, spec: WorldSpec = DEFAULT_SPEC):
        if cfg.frame_stack != 1:
            raise ValueError(f"network.core=gru reads one view per step: frame_stack must be 1, got {cfg.frame_stack}")
        super().__init__(cfg, spec)
        self.memory = nn.GRU(cfg.hidden, cfg.hidden, batch_first=True)

    def q_sequence(self, views: torch.Tensor, text: torch.Tensor, state: torch.Tensor | None = None,
                   real: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Q-values of every step of B sequences: views (B, T, V, V, 4), text (B, text_hidden) from
        `encode_mission`, state (1, B, hidden) or None for zeros -> ((B, T, n_actions), state after T).

        real (B, T) bool, optional: the views worth encoding. The others (padding past an episode's end)
        get zero features: they come after every real step, so they change no real step's Q-value, and
        a batch padded to its longest episode skips most of its encoder work."""
        b, t = views.shape[:2]
        frames = views.reshape(b * t, 1, *views.shape[2:])
        # Every step of a sequence shares its mission: repeat its encoding, not the encoder.
        texts = text.repeat_interleave(t, dim=0)
        if real is None:
            x = self.hidden_features(frames, texts).view(b, t, -1)
        else:
            keep = real.reshape(-1)
            x = views.new_zeros((b * t, self.trunk.out_features), dtype=texts.dtype)
            x = x.index_put((keep,), self.hidden_features(frames[keep], texts[keep])).view(b, t, -1)
        remembered, state = self.memory(x, state)
        return self.head(x + remembered), state

    def forward(self, views: torch.Tensor, mission: torch.Tensor) -> torch.Tensor:
        """(B, T, V, V, 4) episodes from their first view, (B, L) missions -> (B, T, n_actions)."""
        return self.q_sequence(views, self.encode_mission(mission))[0]


def q_network(cfg: NetworkConfig, spec: WorldSpec = DEFAULT_SPEC) -> QNetwork:
    """The Q-network `cfg.core` names: the frame-stack network or the recurrent one."""
    return RecurrentQNetwork(cfg, spec) if cfg.recurrent else QNetwork(cfg, spec)


def sequence_dqn_terms(
    online: RecurrentQNetwork,
    target: RecurrentQNetwork,
    frames: torch.Tensor,
    mission: torch.Tensor,
    action: torch.Tensor,
    reward: torch.Tensor,
    discount: torch.Tensor,
    next_step: torch.Tensor,
    mask: torch.Tensor,
    weights: torch.Tensor,
    huber_delta: float = 1.0,
    double: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The double-DQN n-step loss over B whole episodes, padded to T steps: (loss, |td| (B, T) detached
    and 0 on padding, mean Q of the taken actions, mean target).

    frames (B, T+1, V, V, 4): each episode's frames from its first, padded past its end with copies of
    its final frame; action, reward (the n-step return), discount (gamma^m, or 0 when the n steps reach
    a terminal pick), next_step (t + m, the step whose state the target bootstraps from) and mask (1 on
    the episode's real steps) are (B, T); weights (B,) are the episodes' importance weights. Step t's
    target: y = reward + discount * Q_target(s_{t+m}, a*), a* = argmax Q_online(s_{t+m}) when `double`.
    Both networks unroll from each episode's first view, so Q(s_t) is the value given all the episode
    has shown up to t. The loss is the weighted Huber loss averaged over real steps.
    """
    # Frame 0 of every episode and frame t+1 of each real step t: what the encoders need to see.
    real = torch.cat([torch.ones_like(mask[:, :1]), mask], dim=1) > 0
    q_all, _ = online.q_sequence(frames, online.encode_mission(mission), real=real)  # (B, T+1, A)
    q = q_all[:, :-1].gather(2, action.unsqueeze(2)).squeeze(2)
    with torch.no_grad():
        q_target_all, _ = target.q_sequence(frames, target.encode_mission(mission), real=real)
        at_next = next_step.unsqueeze(2).expand(-1, -1, q_all.shape[2])
        q_next_target = q_target_all.gather(1, at_next)  # (B, T, A): row t holds Q_target(s_{t+m})
        chooser = q_all.detach().gather(1, at_next) if double else q_next_target
        best = chooser.argmax(dim=2, keepdim=True)
        y = reward + discount * q_next_target.gather(2, best).squeeze(2)
    steps = mask.sum().clamp(min=1.0)
    per_step = F.huber_loss(q, y, reduction="none", delta=huber_delta)
    loss = (per_step * mask * weights.unsqueeze(1)).sum() / steps
    td_abs = (y - q).detach().abs() * mask
    return loss, td_abs, (q.detach() * mask).sum() / steps, (y * mask).sum() / steps
