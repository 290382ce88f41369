"""Where an object lay relative to the agent's start, by dead reckoning from the episode's own record.

A BabyAI mission may name a location ("open the door on your left"): seen from where the agent started
and the way it faced then. The view that shows an achieved outcome cannot tell that, but the episode can:
its actions say when the agent turned, and the view before each `forward` says whether the cell ahead
was free (minigrid moves the agent only then). Adding up the moves gives the agent's pose at any frame,
relative to its start; the object it faces there lies one cell ahead of that pose. The location words
that describe that cell follow minigrid's rule (ObjDesc.find_matching_objs): with v the cell relative
to the start and d the start direction, "left" when v . right(d) < 0, "right" when > 0, "in front of
you" when v . d > 0, "behind you" when < 0.

This reads frames and actions only (what the agent saw and did), never what the world recorded as
achieved. It agrees with the level's own judgement for objects that lay in the start room and had not
been moved (picked up and dropped) before the outcome; tests/unit/test_reckoning.py checks it against
minigrid's masks on replayed episodes.
"""
from __future__ import annotations

import numpy as np

from minigrid.core.actions import Actions
from minigrid.core.constants import OBJECT_TO_IDX, STATE_TO_IDX

_LEFT, _RIGHT, _FORWARD = int(Actions.left), int(Actions.right), int(Actions.forward)
_DOOR, _OPEN = OBJECT_TO_IDX["door"], STATE_TO_IDX["open"]
# Minigrid's objects an agent may step onto (an open door is checked apart): what `can_overlap` admits.
_WALKABLE = np.zeros(max(OBJECT_TO_IDX.values()) + 1, bool)
_WALKABLE[[OBJECT_TO_IDX[name] for name in ("empty", "floor", "goal", "lava")]] = True
# Heading h (0 ahead, 1 right, 2 back, 3 left of the start direction) -> unit step (right, ahead).
_STEP = np.array([(0, 1), (1, 0), (0, -1), (-1, 0)], np.int64)


def start_relative_masks(frames: np.ndarray, actions: np.ndarray, view_indices) -> np.ndarray:
    """For each frame index in `view_indices`, the location mask (bit i for babyai_language.LOCS[i]: left,
    right, front, behind) of the cell the agent faces in that frame, seen from the episode's start.

    `frames` (T+1, V, V, 4) BabyAI views, `actions` (T,) the level's action ids; returns (k,) int64."""
    frames, actions = np.asarray(frames), np.asarray(actions, dtype=np.int64)
    idx = np.asarray(view_indices, dtype=np.int64).reshape(-1)
    if idx.size == 0:
        return np.zeros(0, np.int64)
    if idx.min() < 0 or idx.max() > len(actions) or len(frames) < len(actions) + 1:
        raise ValueError(f"view_indices {idx.tolist()} outside an episode of {len(actions)} actions")
    v = frames.shape[1]
    ahead = frames[:-1, v - 2, v // 2][: len(actions)]  # the cell in front before each action
    kind = np.minimum(ahead[:, 0], len(_WALKABLE) - 1)
    free = _WALKABLE[kind] | ((kind == _DOOR) & (ahead[:, 2] == _OPEN))
    turn = np.where(actions == _RIGHT, 1, np.where(actions == _LEFT, -1, 0))
    heading = np.concatenate([[0], np.cumsum(turn)]) % 4  # (T+1,) heading at each frame
    moved = (actions == _FORWARD) & free
    steps = _STEP[heading[:-1]] * moved[:, None]
    pos = np.concatenate([np.zeros((1, 2), np.int64), np.cumsum(steps, axis=0)])  # (T+1, 2) at each frame
    cell = pos[idx] + _STEP[heading[idx]]
    right, front = cell[:, 0], cell[:, 1]
    return ((right < 0) * 1 | (right > 0) * 2 | (front > 0) * 4 | (front < 0) * 8).astype(np.int64)
