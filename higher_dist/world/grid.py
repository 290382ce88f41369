"""The batched FetchAttr gridworld: B environments stepped together with numpy array operations.

Layout. Each env's room is `room_size` x `room_size` free cells inside a one-cell wall ring, stored
in a grid padded by `view_size - 1` unseen cells on every side, so that a view never leaves the
array and needs no bounds checks. A cell is one little-endian uint32 whose four bytes are the view
channels `[kind, color, shade, size]`; gathering uint32 cells and reinterpreting them as bytes
builds the whole `(B, V, V, 4)` view in a single fancy-indexing gather. The agent is not stored in
the grid (its own cell shows what lies under it: empty); its position is one flat index into the
grid array of all envs, so moving and viewing are plain integer additions.

Directions: 0 up (north, row - 1), 1 right (east), 2 down, 3 left; action 1 (right) turns
clockwise (+1), action 0 (left) counter-clockwise. Positions `(row, col)` count the wall ring:
the free cells are rows and columns 1..room_size.

View: the `V x V` cells ahead, agent at row V-1, column V//2, facing up. No occlusion: walls and
objects do not hide what lies behind them (the paper's room is open; keeping it simple keeps the
hot path one gather).

Seeds: env i of `BatchedFetchAttr(cfg, B, seed)` draws from its own generator
`np.random.default_rng([seed, i])`, or from `np.random.default_rng(env_seeds[i])` when `env_seeds`
is given. So env i of a batch equals a batch of one built with `env_seeds=[[seed, i]]`, and a run is
reproducible whatever the batch size. A pick leaves the grid unchanged: the episode is over and its
last view is never bootstrapped from.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from higher_dist.config import WorldConfig
from higher_dist.world import language
from higher_dist.world.objects import ObjectSpace
from higher_dist.world.spec import (  # noqa: F401  (the encodings, re-exported for the world's users)
    ACTION_FORWARD, ACTION_LEFT, ACTION_NAMES, ACTION_PICK, ACTION_RIGHT, KIND_BALL, KIND_EMPTY, KIND_KEY, KIND_UNSEEN,
    KIND_WALL, N_ACTIONS, RUNNING, SUCCESS, TIMEOUT, WRONG_PICK,
)

_CELL_DTYPE = np.dtype("<u4")  # little-endian so that the bytes read [kind, color, shade, size]
_EMPTY_CELL = KIND_EMPTY
_WALL_CELL = KIND_WALL
DIRECTION_VECTORS = np.array([(-1, 0), (0, 1), (1, 0), (0, -1)])  # (drow, dcol): up, right, down, left
_TURN = np.array([-1, 1, 0, 0])  # direction change per action


def check_actions(actions, batch_size: int, action_names: tuple[str, ...]) -> np.ndarray:
    """One integer action per env of a batched world, each one of `action_names`; else ValueError."""
    a = np.asarray(actions)
    if a.dtype.kind not in "iu":
        raise ValueError(f"actions: must be integers, got dtype {a.dtype}")
    if a.shape != (batch_size,):
        raise ValueError(f"actions: must have shape ({batch_size},), got {a.shape}")
    if a.min() < 0 or a.max() >= len(action_names):
        raise ValueError(f"actions: must be in 0..{len(action_names) - 1} ({', '.join(action_names)}), "
                         f"got values {np.unique(a).tolist()}")
    return a


def object_cells(attrs) -> np.ndarray:
    """Grid cell codes (uint32) of objects `attrs (n, 4)` = (color, type, shade, size)."""
    a = np.asarray(attrs, dtype=np.int64).reshape(-1, 4)
    kind = KIND_KEY + a[:, 1]
    return (kind | (a[:, 0] + 1) << 8 | (a[:, 2] + 1) << 16 | (a[:, 3] + 1) << 24).astype(_CELL_DTYPE)


def cell_attrs(cells) -> np.ndarray:
    """Inverse of `object_cells`: object cell codes `(n,)` -> attributes `(n, 4)` int8."""
    b = np.ascontiguousarray(cells, dtype=_CELL_DTYPE).view(np.uint8).reshape(-1, 4).astype(np.int8)
    return np.stack([b[:, 1] - 1, b[:, 0] - KIND_KEY, b[:, 2] - 1, b[:, 3] - 1], axis=1)


def pick_reward(picked, goal, shaping: bool) -> np.ndarray:
    """The reward of picking objects `picked (n, 4)` when the goal is `goal (n, 4)`: 1 for a copy of the
    goal, else 0; with reward shaping (DQN+reward), 0.25 per attribute the picked object shares with it.
    What `BatchedFetchAttr.step` pays and what a received episode's last reward must be."""
    matches = (np.asarray(picked) == np.asarray(goal)).sum(axis=1)
    return (0.25 * matches if shaping else matches == 4).astype(np.float32)


@dataclass
class StepResult:
    """What one batched step returns. Per-episode fields describe the episode the step belonged to
    (before any reset), so a consumer can close that episode without keeping its own copy."""
    view: np.ndarray  # (B, V, V, 4) uint8: next observation; the new episode's first for finished envs
    mission: np.ndarray  # (B, L) int64: mission of the episode now running (new one where reset)
    reward: np.ndarray  # (B,) float32
    terminated: np.ndarray  # (B,) bool: a pick ended the episode
    truncated: np.ndarray  # (B,) bool: the step limit ended it (a time-out, not a terminal state)
    final_view: np.ndarray  # (B, V, V, 4) uint8: view reached by this step, before any reset (the
    #                         same array as `view` when no env finished this step)
    outcome: np.ndarray  # (B,) int8: SUCCESS / WRONG_PICK / TIMEOUT, RUNNING (-1) if it goes on
    length: np.ndarray  # (B,) int32: steps taken in the episode so far, this one included
    picked: np.ndarray  # (B, 4) int8: attributes of the object picked by this step, -1 if none
    goal: np.ndarray  # (B, 4) int8: goal of the episode this step belonged to (ground truth)
    mission_done: np.ndarray  # (B, L) int64: mission of the episode this step belonged to
    final_dir: np.ndarray  # (B,) int64: direction reached by this step, before any reset
    pick_step: np.ndarray  # (B,) int32: index of the step of the episode that picked `picked` (the
    #                        pick hindsight describes), -1 if none. FetchAttr: a pick ends the episode,
    #                        so it is length - 1 for picks; worlds where picks go on report the first.
    # Outcomes after the first (BabyAI levels; None on FetchAttr, whose episodes have one).
    later_achieved: np.ndarray | None = None  # (B, MAX_LATER, 4) int8, -1 rows for none
    later_step: np.ndarray | None = None  # (B, MAX_LATER) int32, -1 for none

    @property
    def done(self) -> np.ndarray:
        return self.terminated | self.truncated


class BatchedFetchAttr:
    """B FetchAttr environments stepped together; finished ones are reset in place by `step`.

    Arrays handed out (views, missions, goals) are never written to afterwards: state arrays are
    replaced, not edited, when envs reset, so callers may keep them without copying.
    """

    def __init__(self, cfg: WorldConfig, batch_size: int, seed: int = 0, goal_set: str = "train",
                 env_seeds=None):
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
            raise ValueError(f"batch_size: must be an integer >= 1, got {batch_size!r}")
        self.space = ObjectSpace(cfg)  # validates cfg
        self.cfg, self.batch_size, self.goal_set = cfg, int(batch_size), goal_set
        self._pool = self.space.objects(goal_set)
        self._pool_cells = object_cells(self._pool)
        self._init_seeds(seed, env_seeds)

        room, view = cfg.room_size, cfg.view_size
        self._pad = view - 1  # the farthest a view reaches from the agent, forward
        self._height = room + 2 + 2 * self._pad
        self._cells_per_env = self._height * self._height
        # Offsets, in flat cells, of the view cells and of the cell in front, per direction.
        rows = np.arange(view)[:, None]
        cols = np.arange(view)[None, :]
        ahead, right = view - 1 - rows, cols - view // 2
        right_of = np.array([(0, 1), (1, 0), (0, -1), (-1, 0)])  # the agent's right, per direction
        dr = ahead[None] * DIRECTION_VECTORS[:, 0, None, None] + right[None] * right_of[:, 0, None, None]
        dc = ahead[None] * DIRECTION_VECTORS[:, 1, None, None] + right[None] * right_of[:, 1, None, None]
        self._view_offsets = dr * self._height + dc  # (4, V, V)
        self._front_offsets = DIRECTION_VECTORS[:, 0] * self._height + DIRECTION_VECTORS[:, 1]  # (4,)
        self._env_base = np.arange(self.batch_size) * self._cells_per_env
        # Flat offsets of the free cells, in the order interior cell k = row * room + col.
        k = np.arange(room * room)
        self._interior = (k // room + 1 + self._pad) * self._height + (k % room + 1 + self._pad)

        grid = np.zeros((self.batch_size, self._height, self._height), dtype=_CELL_DTYPE)
        inner = slice(self._pad, self._pad + room + 2)
        grid[:, inner, inner] = _WALL_CELL  # the wall ring; resets only rewrite the free cells
        self._grid = grid.reshape(-1)  # flat over all envs: one gather serves the whole batch
        self._pos = self._env_base + self._interior[0]  # flat index of each agent
        self._dir = np.zeros(self.batch_size, dtype=np.int64)
        self._steps = np.zeros(self.batch_size, dtype=np.int32)
        self._goal = np.full((self.batch_size, 4), -1, dtype=np.int8)
        self._mission = np.zeros((self.batch_size, language.MISSION_LEN), dtype=np.int64)
        self._all = np.arange(self.batch_size)
        # One draw call per env reset for all the small integers: object kinds, goal, direction, wording.
        self._draw_highs = np.array([len(self._pool)] * cfg.n_objects + [cfg.n_objects, 4, language.N_VARIANTS])
        self._started = False

    # ----------------------------------------------------------------------------------- seeding

    def _init_seeds(self, seed, env_seeds) -> None:
        if env_seeds is None:
            env_seeds = [[int(seed), i] for i in range(self.batch_size)]
        elif len(env_seeds) != self.batch_size:
            raise ValueError(f"env_seeds: needs one seed per env ({self.batch_size}), got {len(env_seeds)}")
        self._rngs = [np.random.default_rng(s) for s in env_seeds]

    # ------------------------------------------------------------------------------ observations

    def _views(self, envs=None) -> np.ndarray:
        if envs is None:
            cells = self._grid[self._pos[:, None, None] + self._view_offsets[self._dir]]
        else:
            cells = self._grid[self._pos[envs, None, None] + self._view_offsets[self._dir[envs]]]
        v = self.cfg.view_size
        return cells.view(np.uint8).reshape(len(cells), v, v, 4)

    @property
    def mission(self) -> np.ndarray:
        return self._mission

    @property
    def goal(self) -> np.ndarray:
        return self._goal

    @property
    def agent_pos(self) -> np.ndarray:
        """(B, 2) (row, col) of each agent, the wall ring counted (free cells are 1..room_size)."""
        local = self._pos - self._env_base
        return np.stack([local // self._height - self._pad, local % self._height - self._pad], axis=1)

    @property
    def agent_dir(self) -> np.ndarray:
        return self._dir.copy()

    @property
    def steps(self) -> np.ndarray:
        return self._steps.copy()

    # ---------------------------------------------------------------------------------- resetting

    def reset(self, seed: int | None = None):
        """Start a new episode in every env; `seed` re-seeds all envs by the (seed, i) scheme.
        Returns (view (B, V, V, 4) uint8, mission (B, L) int64)."""
        if seed is not None:
            self._init_seeds(seed, None)
        self._reset_envs(self._all)
        self._started = True
        return self._views(), self._mission

    def _reset_envs(self, envs: np.ndarray) -> None:
        """New episodes for `envs`: per-env draws from each env's own generator, then batched writes."""
        n_obj, n_free, highs = self.cfg.n_objects, self.cfg.room_size ** 2, self._draw_highs
        cells = np.empty((len(envs), n_obj + 1), dtype=np.int64)
        draws = np.empty((len(envs), n_obj + 3), dtype=np.int64)
        for row, env in enumerate(envs.tolist()):
            rng = self._rngs[env]
            cells[row] = rng.choice(n_free, n_obj + 1, replace=False)  # agent first, then objects
            draws[row] = rng.integers(0, highs)
        kinds, goal_pick = draws[:, :n_obj], draws[:, n_obj]
        base = self._env_base[envs][:, None]
        self._grid[base + self._interior] = _EMPTY_CELL
        self._grid[base + self._interior[cells[:, 1:]]] = self._pool_cells[kinds]
        self._pos[envs] = base[:, 0] + self._interior[cells[:, 0]]
        self._dir = self._dir.copy()  # a StepResult's final_dir may be this array: replace, not edit
        self._dir[envs] = draws[:, n_obj + 1]
        self._steps[envs] = 0
        goal_index = kinds[np.arange(len(envs)), goal_pick]
        self._set_goals(envs, self._pool[goal_index], language.mission_tokens(self._pool[goal_index],
                                                                               draws[:, n_obj + 2]))

    def _set_goals(self, envs, goals, missions) -> None:
        # Replace rather than edit: arrays handed out by earlier steps stay as they were.
        self._goal = self._goal.copy()
        self._goal[envs] = goals
        self._mission = self._mission.copy()
        self._mission[envs] = missions

    def set_state(self, env_index: int, agent_pos, agent_dir: int, objects, goal, mission=None):
        """Lay out env `env_index` by hand (tests, demos): agent (row, col) and direction, objects as
        [((row, col), (color, type, shade, size)), ...], goal attributes, and optionally the mission
        (default: the first grammar variant describing the goal). Starts a fresh episode there."""
        room = self.cfg.room_size
        if not 0 <= env_index < self.batch_size:
            raise ValueError(f"env_index: must be in [0, {self.batch_size}), got {env_index}")
        if agent_dir not in range(4):
            raise ValueError(f"agent_dir: must be 0..3, got {agent_dir}")
        taken = set()
        for row, col in [tuple(agent_pos)] + [tuple(p) for p, _ in objects]:
            if not (1 <= row <= room and 1 <= col <= room) or (row, col) in taken:
                raise ValueError(f"set_state: position {(row, col)} is outside the room or taken twice")
            taken.add((row, col))
        base = self._env_base[env_index]
        to_flat = lambda rc: base + (rc[0] + self._pad) * self._height + rc[1] + self._pad  # noqa: E731
        self._grid[base + self._interior] = _EMPTY_CELL
        for position, attrs in objects:
            self._grid[to_flat(position)] = object_cells([attrs])[0]
        self._pos[env_index] = to_flat(agent_pos)
        self._dir = self._dir.copy()
        self._dir[env_index] = agent_dir
        self._steps[env_index] = 0
        goal = np.asarray(goal, dtype=np.int8).reshape(1, 4)
        if mission is None:
            mission = language.mission_tokens(goal, [0])[0]
        self._set_goals([env_index], goal, np.asarray(mission, dtype=np.int64))
        self._started = True

    @property
    def view_size(self) -> int:
        return self.cfg.view_size

    @property
    def max_steps(self) -> int:
        return self.cfg.max_steps

    def view(self) -> np.ndarray:
        """The current observation of every env, (B, V, V, 4) uint8."""
        return self._views()

    def room_cells(self, env_index: int) -> np.ndarray:
        """The whole room of one env with its wall ring, (room+2, room+2, 4) uint8 in view channels
        (the agent is not drawn). For tests, debugging and rendering; not the agent's observation."""
        grid = self._grid.reshape(self.batch_size, self._height, self._height)[env_index]
        inner = slice(self._pad, self._height - self._pad)
        return np.ascontiguousarray(grid[inner, inner]).view(np.uint8).reshape(
            self.cfg.room_size + 2, self.cfg.room_size + 2, 4)

    # ------------------------------------------------------------------------------------ stepping

    def _check_actions(self, actions) -> np.ndarray:
        return check_actions(actions, self.batch_size, ACTION_NAMES).astype(np.int64, copy=False)

    def step(self, actions) -> StepResult:
        """Apply one action per env; finished envs start a new episode in place (see StepResult)."""
        if not self._started:
            raise RuntimeError("BatchedFetchAttr.step: call reset() first")
        a = self._check_actions(actions)
        front = self._pos + self._front_offsets[self._dir]
        front_cell = self._grid[front]
        front_kind = front_cell & 0xFF
        # Forward moves only onto empty cells: walls and objects block.
        moves = (a == ACTION_FORWARD) & (front_kind == KIND_EMPTY)
        self._pos = np.where(moves, front, self._pos)
        self._dir = (self._dir + _TURN[a]) & 3
        picks = (a == ACTION_PICK) & (front_kind >= KIND_KEY)  # a pick on an empty cell does nothing
        self._steps += 1
        truncated = (self._steps >= self.cfg.max_steps) & ~picks
        done = picks | truncated

        reward = np.zeros(self.batch_size, dtype=np.float32)
        outcome = np.full(self.batch_size, RUNNING, dtype=np.int8)
        picked = np.full((self.batch_size, 4), -1, dtype=np.int8)
        if picks.any():
            # Any copy of the goal counts: compare attribute codes, not object identities.
            picked[picks] = cell_attrs(front_cell[picks])
            success = (picked[picks] == self._goal[picks]).all(axis=1)
            reward[picks] = pick_reward(picked[picks], self._goal[picks], self.cfg.reward_shaping)
            outcome[picks] = np.where(success, SUCCESS, WRONG_PICK)
        outcome[truncated] = TIMEOUT
        final_view = self._views()
        length, goal, mission_done = self._steps.copy(), self._goal, self._mission
        view, final_dir = final_view, self._dir
        if done.any():
            finished = np.flatnonzero(done)
            self._reset_envs(finished)
            view = final_view.copy()
            view[finished] = self._views(finished)
        return StepResult(view=view, mission=self._mission, reward=reward, terminated=picks,
                          truncated=truncated, final_view=final_view, outcome=outcome, length=length,
                          picked=picked, goal=goal, mission_done=mission_done, final_dir=final_dir,
                          pick_step=np.where(picks, length - 1, -1).astype(np.int32))


class FetchAttrEpisodes:
    """What a FetchAttr episode means (the family's part of world/episode_rules.py): a pick ends the
    episode, every object names all four attributes, and the reward is `pick_reward`'s."""

    @staticmethod
    def achieve_action(spec) -> int:
        """The action that achieves an outcome: a pick."""
        return ACTION_PICK

    @staticmethod
    def not_shown_reason(spec) -> str:
        return "picked_not_in_front"

    @staticmethod
    def picks(spec, b) -> np.ndarray:
        """Which episodes picked: any that did not time out (their pick_step is checked with the outcome)."""
        return b.outcome != TIMEOUT

    @staticmethod
    def outcome_attributes_ok(spec, attrs) -> np.ndarray:
        """A picked object names all four attributes."""
        return (attrs >= 0).all(axis=1)

    @staticmethod
    def shown(spec, b, step, attrs) -> np.ndarray:
        """Whether the picked object `attrs` sits in the cell in front on the frame before the pick."""
        return (spec.front_object(b.frame_at(step)) == attrs).all(axis=1)

    @staticmethod
    def attributes_ok(spec, b, picks) -> np.ndarray:
        picked_ok = np.where(picks, (b.picked >= 0).all(axis=1), (b.picked == -1).all(axis=1))
        return (b.goal >= 0).all(axis=1) & picked_ok

    @staticmethod
    def cells_ok(spec, frames) -> np.ndarray:
        """An object cell shows colour, shade and size; unseen, empty and wall cells show none."""
        attrs_set = frames[..., 1:] > 0
        return np.where(frames[..., 0] >= KIND_KEY, attrs_set.all(axis=-1), ~attrs_set.any(axis=-1))

    @staticmethod
    def outcome_ok(spec, b, last_action) -> np.ndarray:
        """A time-out runs to the step limit without a pick; otherwise the last step is the pick, a success
        exactly when the picked object is the goal."""
        match = (b.picked == b.goal).all(axis=1)
        return np.where(b.outcome == TIMEOUT, (b.lengths == spec.max_steps) & (b.pick_step == -1),
                        (last_action == ACTION_PICK) & (b.pick_step == b.lengths - 1) & (match == (b.outcome == SUCCESS)))

    @staticmethod
    def reward(spec, b) -> np.ndarray:
        """The last step's reward of an original episode: nothing on a time-out, else the pick's."""
        return np.where(b.outcome == TIMEOUT, 0.0, pick_reward(b.picked, b.goal, spec.reward_shaping))

    @staticmethod
    def mission_ok(spec, named) -> bool:
        """The mission names an object of this world's attribute values (a small world uses a subset)."""
        return all(int(v) in values for v, values in zip(named, spec.world_values))


FETCHATTR_EPISODES = FetchAttrEpisodes()
