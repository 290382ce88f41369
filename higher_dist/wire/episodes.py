"""Episode batches on the wire: a list of `Episode`s as a handful of concatenated arrays.

One `episodes` message carries N episodes as:
    frames (F, V, V, 4) uint8     every episode's T+1 frames, one after another (F = sum(T) + N)
    actions (S,) uint8, rewards (S,) float32   every episode's T steps (S = sum(T))
    lengths (N,) int32            T of each episode
    mission (N, L) int64, outcome (N,) uint8, picked (N, 4) int8, goal (N, 4) int8, relabelled (N,) uint8,
    actor_id (N,) int32, weights_version (N,) int64
Concatenation keeps the frame count independent of N (11 frames per batch however many episodes) and lets
the codec scan each kind of value once per batch.

The codec already enforced dtypes, shapes, shared dimensions and the schema's value ranges; `unpack_episodes`
adds what depends on the run (max_steps, view size, vocabulary) and the cross-array bookkeeping.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from higher_dist.learning.episode import Episode
from higher_dist.wire.codec import Message, WireError


def pack_episodes(episodes: Sequence[Episode]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(fields, arrays) for `codec.encode("episodes", fields, arrays)`."""
    if not episodes:
        raise ValueError("pack_episodes: an episodes message needs at least one episode")
    n = len(episodes)
    lengths = np.fromiter((ep.length for ep in episodes), dtype=np.int32, count=n)
    for ep in episodes:
        if ep.frames.shape[0] != ep.length + 1 or ep.rewards.shape[0] != ep.length:
            raise ValueError("pack_episodes: an episode of %d actions needs %d frames and %d rewards, has %d and %d"
                             % (ep.length, ep.length + 1, ep.length, ep.frames.shape[0], ep.rewards.shape[0]))
    arrays = {
        "frames": np.concatenate([ep.frames for ep in episodes]).astype(np.uint8, copy=False),
        "actions": np.concatenate([ep.actions for ep in episodes]).astype(np.uint8, copy=False),
        "rewards": np.concatenate([ep.rewards for ep in episodes]).astype(np.float32, copy=False),
        "lengths": lengths,
        "mission": np.stack([ep.mission for ep in episodes]).astype(np.int64, copy=False),
        "outcome": np.array([ep.outcome for ep in episodes], dtype=np.uint8),
        "picked": np.stack([ep.picked for ep in episodes]).astype(np.int8, copy=False),
        "goal": np.stack([ep.goal for ep in episodes]).astype(np.int8, copy=False),
        "relabelled": np.array([ep.relabelled for ep in episodes], dtype=np.uint8),
        "actor_id": np.array([ep.actor_id for ep in episodes], dtype=np.int32),
        "weights_version": np.array([ep.weights_version for ep in episodes], dtype=np.int64),
    }
    return {"count": n}, arrays


def unpack_episodes(msg: Message, max_steps: int, *, vocab_size: int, view_size: int = 7,
                    mission_len: int | None = None) -> list[Episode]:
    """Episodes from a decoded `episodes` message, checked against the run's world; WireError otherwise.

    Each episode owns fresh, writable copies of its arrays, so the replay may keep one episode without
    pinning the whole received batch in memory.
    """
    if msg.type != "episodes":
        raise WireError("unknown_type", "expected episodes, got %s" % msg.type)
    a = msg.arrays
    frames, actions, rewards, lengths = a["frames"], a["actions"], a["rewards"], a["lengths"]
    n = lengths.shape[0]
    if frames.shape[1:] != (view_size, view_size, 4):
        raise WireError("shape", "frames of %s, this run's view is %dx%dx4" % (frames.shape[1:], view_size, view_size))
    if mission_len is not None and a["mission"].shape[1] != mission_len:
        raise WireError("shape", "missions of %d tokens, expected %d" % (a["mission"].shape[1], mission_len))
    if lengths.min() < 1 or lengths.max() > max_steps:
        raise WireError("range", "episode lengths must lie in [1, %d]" % max_steps)
    steps = int(lengths.sum(dtype=np.int64))
    if steps != actions.shape[0] or steps + n != frames.shape[0]:
        raise WireError("shape", "lengths sum to %d steps; got %d actions and %d frames (expected %d)"
                        % (steps, actions.shape[0], frames.shape[0], steps + n))
    if a["mission"].max() >= vocab_size:
        raise WireError("range", "mission token >= vocabulary size %d" % vocab_size)
    episodes = []
    step_start = frame_start = 0
    for i in range(n):
        length = int(lengths[i])
        episodes.append(Episode(
            frames=frames[frame_start:frame_start + length + 1].copy(),
            actions=actions[step_start:step_start + length].copy(),
            rewards=rewards[step_start:step_start + length].copy(),
            mission=a["mission"][i].copy(),
            outcome=int(a["outcome"][i]),
            picked=a["picked"][i].copy(),
            goal=a["goal"][i].copy(),
            relabelled=bool(a["relabelled"][i]),
            actor_id=int(a["actor_id"][i]),
            weights_version=int(a["weights_version"][i]),
        ))
        step_start += length
        frame_start += length + 1
    return episodes
