"""Episode batches on the wire: a list of `Episode`s as a handful of concatenated arrays.

One `episodes` message carries N episodes as:
    frames (F, V, V, 4) uint8     every episode's T+1 frames, one after another (F = sum(T) + N)
    actions (S,) uint8, rewards (S,) float32   every episode's T steps (S = sum(T))
    lengths (N,) int32            T of each episode
    mission (N, L) int64, outcome (N,) uint8, picked (N, 4) int8, goal (N, 4) int8, pick_step (N,) int32,
    relabelled (N,) uint8, actor_id (N,) int32, weights_version (N,) int64
Concatenation keeps the frame count independent of N (11 frames per batch however many episodes) and lets
the codec scan each kind of value once per batch.

The codec already enforced dtypes, shapes, shared dimensions and the schema's value ranges. `unpack_episodes`
checks, once, at the boundary, everything else the run depends on, against the run's `WorldSpec`: the batch's
structure (view size, mission length, lengths that add up) drops the whole message; each episode's own values
(tokens, grammar, attributes, cells, outcome versus rewards, pick and last action, the relabelled flag, ids)
drop that episode only, counted under one of `EPISODE_REJECTS`. Nothing that passes can make replay, the
generator or the networks raise later.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from higher_dist.learning.episode import Episode
from higher_dist.wire.codec import Message, WireError
from higher_dist.world.spec import ACTION_PICK, KIND_KEY, SUCCESS, TIMEOUT, WRONG_PICK, WorldSpec

# Why one episode of an otherwise well-formed batch was dropped (counter names, one per check).
EPISODE_REJECTS = (
    "episode_length",  # length outside [1, max_steps]
    "mission_token",  # a word id outside the vocabulary
    "mission_grammar",  # not a sentence of the language (all-PAD, ungrammatical, unknown object)
    "mission_goal",  # an original episode whose mission does not name its goal
    "attribute",  # goal or picked attribute outside the world's values
    "cell",  # a view cell this world cannot show
    "action",  # an action this world does not have (the schema admits every world's)
    "outcome",  # outcome inconsistent with length, the pick's step and action, picked or goal
    "reward",  # rewards inconsistent with outcome (or the shaping rule)
    "picked_not_in_front",  # the picked object is not in the cell in front before the pick
    "relabel_origin",  # a relabelled episode from a sender that may not relabel
    "relabel_inconsistent",  # a relabelled copy that is not a wrong pick rewarded 1, or names its own goal
    "actor_id",  # an actor id outside the run's actors
)


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
        "pick_step": np.array([ep.pick_step for ep in episodes], dtype=np.int32),
        "relabelled": np.array([ep.relabelled for ep in episodes], dtype=np.uint8),
        "actor_id": np.array([ep.actor_id for ep in episodes], dtype=np.int32),
        "weights_version": np.array([ep.weights_version for ep in episodes], dtype=np.int64),
    }
    return {"count": n}, arrays


def unpack_episodes(msg: Message, spec: WorldSpec, *, reject=None, allow_relabelled: bool = True,
                    n_actors: int | None = None) -> list[Episode]:
    """Episodes from a decoded `episodes` message, checked against the run's world.

    A structural fault of the batch raises WireError (drop the message). A fault of one episode calls
    `reject(reason)` and drops that episode; without `reject` it raises WireError(reason) instead.
    allow_relabelled: whether this sender may send relabelled copies (only the relabeler may).
    Each episode owns fresh, writable copies of its arrays, so the replay may keep one episode without
    pinning the whole received batch in memory.
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
                actor_id=int(a["actor_id"][i]),
                weights_version=int(a["weights_version"][i]),
            ))
        step_start += length
        frame_start += length + 1
    return episodes


def _episode_faults(a: dict, spec: WorldSpec, allow_relabelled: bool, n_actors: int | None) -> list[str]:
    """Per episode, the first failed check's reason ("" when it passes). Vectorised over the batch,
    except the grammar, which parses each mission once."""
    lengths = a["lengths"].astype(np.int64)
    n = lengths.shape[0]
    ends = np.cumsum(lengths)  # one past each episode's last step
    starts = ends - lengths
    frame_starts = starts + np.arange(n)  # each episode's first frame
    outcome, picked, goal = a["outcome"].astype(np.int64), a["picked"].astype(np.int64), a["goal"].astype(np.int64)
    pick_step = a["pick_step"].astype(np.int64)
    relabelled = a["relabelled"].astype(bool)
    rewards, actions = a["rewards"], a["actions"]
    babyai = spec.family == "babyai"
    reasons = [""] * n

    def flag(mask: np.ndarray, reason: str) -> None:
        for i in np.flatnonzero(mask):
            if not reasons[i]:
                reasons[i] = reason

    def at(values: np.ndarray, index: np.ndarray) -> np.ndarray:  # values[index], safe on empty arrays
        return values[np.clip(index, 0, max(len(values) - 1, 0))] if len(values) else np.zeros(n, values.dtype)

    flag((lengths < 1) | (lengths > spec.max_steps), "episode_length")
    flag((a["mission"] >= spec.vocab_size).any(axis=1), "mission_token")
    step_episode = np.repeat(np.arange(n), lengths) if n else np.zeros(0, np.int64)
    flag(np.bincount(step_episode[actions >= spec.n_actions], minlength=n) > 0, "action")
    allowed_attr = spec.attr_allowed()
    cols = np.arange(4)
    # What says an object was picked: the pick's step on BabyAI (a pick goes on), the outcome on FetchAttr
    # (a pick ends the episode; its pick_step must then agree, checked with the outcome below).
    picks = (pick_step >= 0) & (pick_step < lengths) if babyai else outcome != TIMEOUT
    flag((pick_step >= lengths) | (pick_step < -1), "outcome")
    value_ok = lambda x: allowed_attr[cols, np.clip(x, -1, allowed_attr.shape[1] - 2) + 1]  # noqa: E731
    if babyai:  # colour, type and location may be unnamed (-1); the article is always 0 or 1
        goal_ok = (value_ok(goal) | (goal == -1)).all(axis=1) & (goal[:, 3] >= 0)
        picked_set = value_ok(picked)[:, [0, 1, 3]].all(axis=1) & (picked[:, 2] == -1)
    else:
        goal_ok = value_ok(goal).all(axis=1) & (goal >= 0).all(axis=1)
        picked_set = value_ok(picked).all(axis=1) & (picked >= 0).all(axis=1)
    flag(~goal_ok | ~np.where(picks, picked_set, (picked == -1).all(axis=1)), "attribute")
    allowed_cell = spec.cell_allowed()
    frames = a["frames"]
    cell_ok = np.ones(frames.shape[:-1], dtype=bool)
    for c in range(frames.shape[-1]):
        cell_ok &= allowed_cell[c, np.minimum(frames[..., c], allowed_cell.shape[1] - 1)]
    if not babyai:  # a FetchAttr object shows all three attributes; unseen, empty and wall show none
        is_object = frames[..., 0] >= KIND_KEY
        attrs_set = frames[..., 1:] > 0
        cell_ok &= np.where(is_object, attrs_set.all(axis=-1), ~attrs_set.any(axis=-1))
    frame_bad = ~cell_ok.reshape(frames.shape[0], -1).all(axis=1)
    flag(np.add.reduceat(frame_bad, frame_starts) > 0 if n else frame_bad[:0], "cell")
    # Outcome versus length, the pick, the last action and the goal.
    last_action = at(actions, ends - 1).astype(np.int64)
    pick_action = at(actions, starts + np.clip(pick_step, 0, lengths - 1)).astype(np.int64)
    flag(picks & (pick_action != ACTION_PICK), "outcome")
    timed_out = lengths == spec.max_steps
    if babyai:  # a wrong pick goes on: originals end in a success (a pick) or the time-out
        outcome_ok = np.where(outcome == TIMEOUT, timed_out, (outcome == SUCCESS) & (last_action == ACTION_PICK))
        outcome_ok |= relabelled  # a copy's own rule (it ends at its pick) is relabel_inconsistent's below
    else:  # a pick ends the episode: it is the last step, a success exactly when it matches the goal
        match = (picked == goal).all(axis=1)
        outcome_ok = np.where(outcome == TIMEOUT, timed_out & (pick_step == -1),
                              (last_action == ACTION_PICK) & (pick_step == lengths - 1) & (match == (outcome == SUCCESS)))
    flag(~outcome_ok, "outcome")
    # Rewards: zero before the last step; the last is the pick's reward.
    early = np.ones(rewards.shape[0], dtype=bool)
    early[(ends - 1)[ends >= 1]] = False
    flag(np.bincount(step_episode[early & (rewards != 0)], minlength=n) > 0, "reward")
    final = at(rewards, ends - 1)
    won = relabelled | (outcome == SUCCESS)
    if spec.reward_shaping:
        expected = np.where(relabelled, 1.0, np.where(outcome == TIMEOUT, 0.0, 0.25 * (picked == goal).sum(axis=1)))
    else:
        expected = np.where(won, spec.pick_reward(lengths), 0.0)
    flag(np.abs(final - expected) > 1e-5, "reward")
    # The picked object sits in the cell in front of the agent on the frame before the pick.
    front = spec.front_object(at(frames, frame_starts + np.clip(pick_step, 0, lengths - 1)))
    columns = spec.picked_columns  # BabyAI's picked object holds colour and type, then location and article
    front_ok = (front[:, :columns] == picked[:, :columns]).all(axis=1)
    flag(picks & ~front_ok, "picked_not_in_front")
    if not allow_relabelled:
        flag(relabelled, "relabel_origin")
    flag(relabelled & ((outcome != WRONG_PICK) | (pick_step != lengths - 1)), "relabel_inconsistent")
    if n_actors is not None:
        flag(a["actor_id"] >= n_actors, "actor_id")
    # The grammar last: the only per-episode Python loop, skipped for episodes already dropped.
    parse = spec.language.parse
    for i in range(n):
        if reasons[i]:
            continue
        named = parse(a["mission"][i])
        if named is None or not (babyai or allowed_attr[cols, named.astype(np.int64) + 1].all()):
            reasons[i] = "mission_grammar"
        elif relabelled[i] and (named.astype(np.int64) == goal[i]).all():
            reasons[i] = "relabel_inconsistent"  # it would store the failed goal as reached
        elif not relabelled[i] and not (named.astype(np.int64) == goal[i]).all():
            reasons[i] = "mission_goal"
    return reasons
