"""Episode batches on the wire: a list of `Episode`s as a handful of concatenated arrays.

One `episodes` message carries N episodes as:
    frames (F, V, V, 4) uint8     every episode's T+1 frames, one after another (F = sum(T) + N)
    actions (S,) uint8, rewards (S,) float32   every episode's T steps (S = sum(T))
    lengths (N,) int32            T of each episode
    mission (N, L) int64, outcome (N,) uint8, picked (N, 4) int8, goal (N, 4) int8, pick_step (N,) int32,
    later_achieved (N, MAX_LATER, 4) int8, later_step (N, MAX_LATER) int32,
    relabelled (N,) uint8, actor_id (N,) int32, weights_version (N,) int64
Concatenation keeps the frame count independent of N (11 frames per batch however many episodes) and lets
the codec scan each kind of value once per batch.

The codec already enforced dtypes, shapes, shared dimensions and the schema's value ranges. `unpack_episodes`
checks, once, at the boundary, everything else the run depends on, against the run's `WorldSpec`: the batch's
structure (view size, mission length, lengths that add up) drops the whole message; each episode's own values
drop that episode only, counted under one of `EPISODE_REJECTS`. This module checks the run's ranges (length,
tokens, actions, attribute and cell values) and who may send what (relabelled copies, actor ids); what an
episode means on its world (grammar, outcome versus rewards, the pick, a copy's consistency) is the world's
check, world/episode_rules.py. Nothing that passes can make replay, the generator or the networks raise later.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from higher_dist.learning.episode import Episode, Withheld
from higher_dist.wire.codec import Message, WireError
from higher_dist.world.episode_rules import EPISODE_FAULTS, episode_faults
from higher_dist.world.spec import WorldSpec

# Why one episode of an otherwise well-formed batch was dropped (counter names, one per check): the
# wire's own checks of ranges and senders, then the world's of meaning (world/episode_rules.py).
EPISODE_REJECTS = (
    "episode_length",  # length outside [1, max_steps]
    "mission_token",  # a word id outside the vocabulary
    "action",  # an action this world does not have (the schema admits every world's)
    "attribute",  # goal or picked attribute outside the world's values (and the world's rule, below)
    "cell",  # a view cell value this world's tables lack (and the world's rule, below)
    "relabel_origin",  # a relabelled episode from a sender that may not relabel
    "actor_id",  # an actor id outside the run's actors
) + tuple(reason for reason in EPISODE_FAULTS if reason not in ("attribute", "cell"))


def pack_episodes(episodes: Sequence[Episode], withheld: Withheld = Withheld()
                  ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(fields, arrays) for `codec.encode("episodes", fields, arrays)`; `withheld`: the relabeler's
    count of originals it kept out of the replay since its last message."""
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
        "pick_step": np.array([ep.pick_step for ep in episodes], dtype=np.int32),
        "later_achieved": np.stack([ep.later_achieved for ep in episodes]).astype(np.int8, copy=False),
        "later_step": np.stack([ep.later_step for ep in episodes]).astype(np.int32, copy=False),
        "relabelled": np.array([ep.relabelled for ep in episodes], dtype=np.uint8),
        "actor_id": np.array([ep.actor_id for ep in episodes], dtype=np.int32),
        "weights_version": np.array([ep.weights_version for ep in episodes], dtype=np.int64),
    }
    fields: dict[str, Any] = {"count": n}
    if withheld != Withheld():
        fields.update(withheld_episodes=withheld.episodes, withheld_frames=withheld.frames)
    return fields, arrays


def unpack_episodes(msg: Message, spec: WorldSpec, *, reject=None, allow_relabelled: bool = True,
                    n_actors: int | None = None) -> list[Episode]:
    """Episodes from a decoded `episodes` message, checked against the run's world.

    A structural fault of the batch raises WireError (drop the message). A fault of one episode calls
    `reject(reason)` and drops that episode; without `reject` it raises WireError(reason) instead.
    allow_relabelled: whether this sender may send relabelled copies and withheld counts (only the
    relabeler may); the counts must add up (`withheld_in` reads them). Each episode owns fresh, writable
    copies of its arrays, so the replay may keep one episode without pinning the whole received batch in
    memory.
    """
    if msg.type != "episodes":
        raise WireError("unknown_type", "expected episodes, got %s" % msg.type)
    a = msg.arrays
    frames, actions, rewards, lengths, mission = a["frames"], a["actions"], a["rewards"], a["lengths"], a["mission"]
    n = lengths.shape[0]
    if frames.shape[1:] != spec.view_shape:
        raise WireError("shape", "frames of %s, this run's view is %s" % (frames.shape[1:], spec.view_shape))
    if mission.shape[1] != spec.mission_len:
        raise WireError("shape", "missions of %d tokens, expected %d" % (mission.shape[1], spec.mission_len))
    steps = int(lengths.sum(dtype=np.int64))
    if steps != actions.shape[0] or steps + n != frames.shape[0]:
        raise WireError("shape", "lengths sum to %d steps; got %d actions and %d frames (expected %d)"
                        % (steps, actions.shape[0], frames.shape[0], steps + n))
    withheld = withheld_in(msg)
    if withheld != Withheld() and not allow_relabelled:
        raise WireError("field", "withheld episodes from a sender that relabels nothing")
    if not withheld.episodes <= withheld.frames <= withheld.episodes * spec.max_steps:
        raise WireError("range", "%d withheld frames for %d withheld episodes of at most %d steps"
                        % (withheld.frames, withheld.episodes, spec.max_steps))
    bad = _episode_faults(a, spec, allow_relabelled, n_actors)
    episodes = []
    step_start = frame_start = 0
    for i in range(n):
        length = int(lengths[i])
        if bad[i]:
            if reject is None:
                raise WireError(bad[i], "episode %d of %d" % (i, n))
            reject(bad[i])
        else:
            episodes.append(Episode(
                frames=frames[frame_start:frame_start + length + 1].copy(),
                actions=actions[step_start:step_start + length].copy(),
                rewards=rewards[step_start:step_start + length].copy(),
                mission=mission[i].copy(), outcome=int(a["outcome"][i]), picked=a["picked"][i].copy(),
                goal=a["goal"][i].copy(), pick_step=int(a["pick_step"][i]), relabelled=bool(a["relabelled"][i]),
                later_achieved=a["later_achieved"][i].copy(), later_step=a["later_step"][i].copy(),
                actor_id=int(a["actor_id"][i]),
                weights_version=int(a["weights_version"][i]),
            ))
        step_start += length
        frame_start += length + 1
    return episodes


def withheld_in(msg: Message) -> Withheld:
    """The originals an `episodes` message says its sender kept out of the replay (none unless it says)."""
    return Withheld(int(msg.fields.get("withheld_episodes", 0)), int(msg.fields.get("withheld_frames", 0)))


def _episode_faults(a: dict, spec: WorldSpec, allow_relabelled: bool, n_actors: int | None) -> list[str]:
    """Per episode, the first failed check's reason ("" when it passes): the run's ranges and who may
    send what here, then the world's meaning (world/episode_rules.py) for the episodes still standing."""
    lengths = a["lengths"].astype(np.int64)
    n = lengths.shape[0]
    reasons = [""] * n

    def flag(mask: np.ndarray, reason: str) -> None:
        for i in np.flatnonzero(mask):
            if not reasons[i]:
                reasons[i] = reason

    flag((lengths < 1) | (lengths > spec.max_steps), "episode_length")
    flag((a["mission"] >= spec.vocab_size).any(axis=1), "mission_token")
    step_episode = np.repeat(np.arange(n), lengths) if n else np.zeros(0, np.int64)
    flag(np.bincount(step_episode[a["actions"] >= spec.n_actions], minlength=n) > 0, "action")
    # Attribute values this world uses, or -1 (none); which may be none is the world's rule.
    allowed_attr = spec.attr_allowed()
    cols = np.arange(4)

    def value_ok(x: np.ndarray) -> np.ndarray:
        return allowed_attr[cols, np.clip(x, -1, allowed_attr.shape[1] - 2) + 1] | (x == -1)

    flag(~(value_ok(a["goal"].astype(np.int64)) & value_ok(a["picked"].astype(np.int64))).all(axis=1), "attribute")
    flag(~value_ok(a["later_achieved"].astype(np.int64)).all(axis=(1, 2)), "attribute")
    allowed_cell = spec.cell_allowed()
    frames = a["frames"]
    cell_ok = np.ones(frames.shape[:-1], dtype=bool)
    for c in range(frames.shape[-1]):
        cell_ok &= allowed_cell[c, np.minimum(frames[..., c], allowed_cell.shape[1] - 1)]
    frame_bad = ~cell_ok.reshape(frames.shape[0], -1).all(axis=1)
    frame_starts = np.cumsum(lengths) - lengths + np.arange(n)
    flag(np.add.reduceat(frame_bad, frame_starts) > 0 if n else frame_bad[:0], "cell")
    if not allow_relabelled:
        flag(a["relabelled"].astype(bool), "relabel_origin")
    if n_actors is not None:
        flag(a["actor_id"] >= n_actors, "actor_id")
    episode_faults(spec, a, reasons)
    return reasons
