"""What the DQN tests share: a small network config and random batches shaped as the replay forms them."""
from __future__ import annotations

import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from higher_dist.config import NetworkConfig
from higher_dist.world.spec import DEFAULT_SPEC

GAMMA = 0.99
SMALL = NetworkConfig(embed_dim=4, conv_channels=(8, 8), frame_stack=2, word_embed_dim=8, text_hidden=8, hidden=16)
needs_cxx = pytest.mark.skipif(not (shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")),
                               reason="torch.compile's CPU backend needs a C++ compiler; none on this machine")


def random_batch(rng: np.random.Generator, b: int, k: int = 2) -> SimpleNamespace:
    """A TransitionBatch look-alike with valid views and missions."""
    def views() -> np.ndarray:
        v = np.zeros((b, k, 7, 7, 4), np.uint8)
        kind = rng.integers(0, 5, (b, k, 7, 7))
        v[..., 0] = kind
        for ch, n in ((1, 7), (2, 6), (3, 6)):
            v[..., ch] = np.where(kind >= 3, rng.integers(1, n, (b, k, 7, 7)), 0)
        return v

    mission = np.zeros((b, 10), np.int64)
    for i, n in enumerate(rng.integers(5, 9, b)):
        mission[i, :n] = rng.integers(3, DEFAULT_SPEC.vocab_size, n)
    return SimpleNamespace(
        indices=np.arange(b), generations=np.zeros(b, np.int64), obs=views(), mission=mission,
        action=rng.integers(0, 4, b), reward=(rng.random(b) < 0.3).astype(np.float32),
        discount=np.where(rng.random(b) < 0.3, 0.0, GAMMA ** 3).astype(np.float32), next_obs=views(),
        weights=rng.uniform(0.2, 1.0, b).astype(np.float32))


def batch_tensors(batch: SimpleNamespace) -> dict[str, torch.Tensor]:
    return {name: torch.from_numpy(getattr(batch, name)) for name in
            ("obs", "mission", "action", "reward", "discount", "next_obs", "weights")}
