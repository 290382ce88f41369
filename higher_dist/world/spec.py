"""The world's encodings, stated once: what every layer that touches observations, missions, actions
or outcomes reads (the Q-network, the generator, replay, the generator's dataset, the wire schema's
limits and the checks on incoming episodes).

Two kinds of knowledge live here:
- module constants: the encodings that are the same on every world (channel layout, kinds, actions,
  outcome codes). Attribute indices are into the *global* tables of `higher_dist.config`, so networks
  have the same input sizes on every world and a checkpoint means the same thing everywhere.
- `WorldSpec`: a small frozen record made from a `WorldConfig` with what a run's world adds (view size,
  episode limit, which attribute values this world uses). Build it with `WorldSpec.of(world_cfg)`.

Two world families share these encodings. `fetchattr` is our own numpy world (world/grid.py). `babyai`
is a Farama Minigrid BabyAI pickup, go-to or open level (world/babyai.py), named by its gymnasium id:
its views are minigrid's (object, colour, state) cells plus a fourth channel that is always 0, its
actions are the level's 7, its missions are the level's own sentences (world/babyai_language.py) and a
described object is (colour, type, location, plural) into that module's tables. The wire schema caps what
any family can send (`MAX_*` below); each run's `WorldSpec` holds its own tighter limits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from higher_dist.config import COLORS, MAX_OUTCOMES, SHADES, SIZES, TYPES, WorldConfig, is_babyai_world
from higher_dist.world import babyai_language, language

# -- view cells: 4 channels [kind, color, shade, size] -------------------------------------------
VIEW_CHANNELS = 4
KIND_UNSEEN, KIND_EMPTY, KIND_WALL, KIND_KEY, KIND_BALL = range(5)
KIND_NAMES = ("unseen", "empty", "wall", "key", "ball")
# Distinct values per channel: kind 0..4; color, shade and size 0 = none, else 1 + global index.
VIEW_CHANNEL_VALUES = (len(KIND_NAMES), 1 + len(COLORS), 1 + len(SHADES), 1 + len(SIZES))

# -- objects: (color, type, shade, size) indices into the global tables, -1 = none -----------------
ATTR_NAMES = ("color", "type", "shade", "size")
ATTR_TABLES = (COLORS, TYPES, SHADES, SIZES)
ATTR_VALUES = tuple(len(t) for t in ATTR_TABLES)

# -- actions ------------------------------------------------------------------------------------
ACTION_LEFT, ACTION_RIGHT, ACTION_FORWARD, ACTION_PICK = range(4)
ACTION_NAMES = ("left", "right", "forward", "pick")
N_ACTIONS = len(ACTION_NAMES)

# -- episode outcomes ---------------------------------------------------------------------------
SUCCESS, WRONG_PICK, TIMEOUT = 0, 1, 2
OUTCOME_NAMES = ("success", "wrong_pick", "timeout")
N_OUTCOMES = len(OUTCOME_NAMES)
RUNNING = -1  # outcome of an env whose episode goes on


# -- the BabyAI family (values minigrid defines; checked against minigrid by tests/unit/test_world_babyai.py)
BABYAI_CHANNEL_VALUES = (11, 6, 3, 1)  # object 0..10, colour 0..5, door state 0..2, padding channel
BABYAI_ACTION_NAMES = ("left", "right", "forward", "pickup", "drop", "toggle", "done")
# The third column: a goal's location index (0..3) or an achieved object's location mask (0..15).
BABYAI_ATTR_VALUES = (len(babyai_language.COLORS), len(babyai_language.TYPES), babyai_language.LOC_MASKS, 2)
BABYAI_FIRST_OBJECT = 5  # minigrid's object index of `key`; key, ball, box follow
BABYAI_DOOR = 4  # minigrid's object index of `door`; its state channel: 0 open, 1 closed, 2 locked
BABYAI_DOOR_OPEN = 0

# -- achieved outcomes: an episode records up to MAX_OUTCOMES distinct ones (the first in `picked` and
# `pick_step`, the rest in `later_achieved` and `later_step`); FetchAttr's episodes have at most one.
MAX_LATER = MAX_OUTCOMES - 1

# -- what the wire admits from any family (the per-run spec checks the run's own limits) -----------
MAX_CHANNEL_VALUES = tuple(max(a, b) for a, b in zip(VIEW_CHANNEL_VALUES, BABYAI_CHANNEL_VALUES))
MAX_ACTIONS = max(N_ACTIONS, len(BABYAI_ACTION_NAMES))
MAX_ATTR_VALUES = tuple(max(a, b) for a, b in zip(ATTR_VALUES, BABYAI_ATTR_VALUES))


@dataclass(frozen=True)
class WorldSpec:
    """What a run's world looks like to everything that is not the world itself."""

    view_size: int
    max_steps: int
    mission_len: int = language.MISSION_LEN
    vocab_size: int = len(language.VOCAB)
    n_actions: int = N_ACTIONS
    n_outcomes: int = N_OUTCOMES
    channel_values: tuple[int, ...] = VIEW_CHANNEL_VALUES
    attr_values: tuple[int, ...] = ATTR_VALUES  # sizes of the global tables (network input ranges)
    # Global indices of the values this world's objects use, per attribute: what a pick or a goal
    # may hold on this world (a small world uses a subset).
    world_values: tuple[tuple[int, ...], ...] = tuple(tuple(range(n)) for n in ATTR_VALUES)
    reward_shaping: bool = False
    family: str = "fetchattr"  # fetchattr | babyai
    level: str = ""  # the BabyAI level's gymnasium id (babyai only)
    level_kind: str = ""  # the verb of every mission of a BabyAI level: pickup, goto or open (babyai only)
    has_heldout: bool = True  # whether some goals are kept out of training (BabyAI levels have none)
    has_locations: bool = False  # whether missions may name a location seen from the start (BabyAI only)

    @classmethod
    def of(cls, world: WorldConfig) -> "WorldSpec":
        if is_babyai_world(world.name):
            return cls._of_babyai(world)
        values = tuple(tuple(table.index(v) for v in getattr(world, field))
                       for table, field in zip(ATTR_TABLES, ("colors", "types", "shades", "sizes")))
        return cls(view_size=world.view_size, max_steps=world.max_steps, world_values=values,
                   reward_shaping=world.reward_shaping)

    @classmethod
    def _of_babyai(cls, world: WorldConfig) -> "WorldSpec":
        from higher_dist.world.babyai_levels import level_facts  # imports minigrid: only when a level is asked for
        facts = level_facts(world.name)
        return cls(view_size=facts.view_size, max_steps=world.max_steps or facts.max_steps,
                   mission_len=babyai_language.MISSION_LEN, vocab_size=len(babyai_language.VOCAB),
                   n_actions=len(BABYAI_ACTION_NAMES), channel_values=BABYAI_CHANNEL_VALUES,
                   attr_values=BABYAI_ATTR_VALUES,
                   world_values=tuple(tuple(range(n)) for n in BABYAI_ATTR_VALUES),
                   reward_shaping=False, family="babyai", level=world.name, level_kind=facts.kind,
                   has_heldout=False, has_locations=facts.has_locations)

    @property
    def language(self):
        """The module of this world's instruction language (world/language.py or world/babyai_language.py):
        or that module's language of the level's kind): both offer VOCAB, MISSION_LEN, encode, decode, parse,
        parse_many, expert_tokens, with_markers, satisfies."""
        return babyai_language.LANGUAGES[self.level_kind] if self.family == "babyai" else language

    @property
    def max_outcomes(self) -> int:
        """How many distinct achieved outcomes an episode of this world may record: a FetchAttr pick ends
        its episode (one); a BabyAI agent goes on reaching, opening or picking until the episode ends."""
        return MAX_OUTCOMES if self.family == "babyai" else 1

    @property
    def outcome_view_offset(self) -> int:
        """Which frame shows an achieved outcome, relative to the step that achieved it: the view before a
        pick or an open (0: the object or door in front), the view after a go-to's step (1: the action
        that reached the object, a turn or a step, is what put it in front)."""
        return 1 if self.level_kind == "goto" else 0

    @property
    def picked_columns(self) -> int:
        """How many leading columns of a picked object's attributes are always set: FetchAttr's 4;
        BabyAI's colour and type (its location is never set, its plural column is 0 or 1)."""
        return 2 if self.family == "babyai" else 4

    @property
    def first_object_kind(self) -> int:
        """The view's kind value of the first pickable object (kinds from here up are objects)."""
        return BABYAI_FIRST_OBJECT if self.family == "babyai" else KIND_KEY

    def front_cell(self, views) -> np.ndarray:
        """The cell in front of the agent in each view `(n, V, V, 4)`, (n, 4) int64 channels."""
        return np.asarray(views)[:, self.view_size - 2, self.view_size // 2].astype(np.int64)

    def front_object(self, views) -> np.ndarray:
        """The object in the cell in front of the agent in each view `(n, V, V, 4)`, as (n, 4) int64
        attributes of this world's language (-1 where that cell holds no object): what a pick from there
        would take, a go-to reach or (a door) an open open. BabyAI describes it by colour and type only
        (-1, -1 for location and article); its doors are type `door`."""
        cell = self.front_cell(views)
        is_object = cell[:, 0] >= self.first_object_kind
        if self.family == "babyai":  # minigrid's kinds after box (goal, lava, agent) are not objects
            is_object &= cell[:, 0] < BABYAI_FIRST_OBJECT + babyai_language.DOOR
            is_door = cell[:, 0] == BABYAI_DOOR
            type_ = np.where(is_door, babyai_language.DOOR, cell[:, 0] - BABYAI_FIRST_OBJECT)
            is_object |= is_door
            attrs = np.stack([cell[:, 1], type_, np.full(len(cell), -1), np.full(len(cell), -1)], axis=1)
        else:
            attrs = np.stack([cell[:, 1] - 1, cell[:, 0] - KIND_KEY, cell[:, 2] - 1, cell[:, 3] - 1], axis=1)
        return np.where(is_object[:, None], attrs, -1)

    def expert_tokens(self, achieved, rng: np.random.Generator) -> np.ndarray:
        """The hindsight expert's missions for achieved outcomes `(n, 4)`: the language's, naming a location
        as well on a level whose missions may name one (the outcome's location mask says which hold)."""
        if self.has_locations:
            return self.language.expert_tokens(achieved, rng, name_location=True)
        return self.language.expert_tokens(achieved, rng)

    def start_locations(self, frames, actions, view_indices) -> np.ndarray:
        """(k,) int64 location masks (bit i for babyai_language.LOCS[i]) of the cell the agent faces in each
        frame `view_indices` of one episode, seen from its start, by dead reckoning from its frames and
        actions (world/reckoning.py); zeros where missions never name a location (FetchAttr, most levels)."""
        if not self.has_locations:
            return np.zeros(len(np.atleast_1d(view_indices)), np.int64)
        from higher_dist.world.reckoning import start_relative_masks  # imports minigrid: only on such a level
        return start_relative_masks(frames, actions, view_indices)

    def fulfilled_by(self, views, missions, locations=None) -> np.ndarray:
        """The object a successful episode's mission was fulfilled by, as far as its pair (the view that
        shows the success, the mission) tells, as (n, 4) int64 achieved attributes for `language.satisfies`.
        FetchAttr: the mission names it whole. BabyAI: colour and type of the object in front (a mission may
        leave them unnamed); its location mask holds the location the mission names (the object is there,
        seen from the start) and those of `locations` (n,) (the pair's `start_locations`) where given; with
        neither, -1 (unknown)."""
        named, _ = self.language.parse_many(missions)
        if self.family != "babyai":
            return named
        out = self.front_object(views)
        mask = np.where(named[:, 2] >= 0, 1 << np.maximum(named[:, 2], 0), 0)
        if locations is not None:
            mask = mask | np.asarray(locations, dtype=np.int64)
        out[:, 2] = np.where(mask > 0, mask, -1)
        return out

    def pick_reward(self, length) -> np.ndarray:
        """The reward of a successful pick on step `length` of an episode (array-valued): 1 on FetchAttr,
        BabyAI's 1 - 0.9 * length / max_steps on its levels. What a relabelled copy's last step gets."""
        length = np.asarray(length, dtype=np.float64)
        if self.family == "babyai":
            return (1.0 - 0.9 * length / self.max_steps).astype(np.float32)
        return np.ones_like(length, dtype=np.float32)

    @property
    def view_shape(self) -> tuple[int, int, int]:
        return (self.view_size, self.view_size, VIEW_CHANNELS)

    @property
    def channel_max(self) -> tuple[int, ...]:
        """Largest value of each view channel (network embedding rows, wire value limits)."""
        return tuple(n - 1 for n in self.channel_values)

    def check_cells(self, frames: np.ndarray, what: str = "views") -> None:
        """ValueError unless `frames` (..., 4) are integers each within its channel's values (an
        out-of-range value would alias another cell's code in the network's embedding)."""
        frames = np.asarray(frames)
        if frames.dtype.kind not in "ui":
            raise ValueError(f"{what}: expected integer cell values, got {frames.dtype}")
        cells = frames.reshape(-1, frames.shape[-1])
        if cells.shape[0] and ((cells.max(axis=0) > np.asarray(self.channel_max)).any()
                               or (frames.dtype.kind == "i" and cells.min() < 0)):
            raise ValueError(f"{what}: channel values out of range [0, {list(self.channel_max)}]")

    def attr_allowed(self) -> np.ndarray:
        """(4, max(attr_values) + 1) bool: entry [a, v + 1] is True when this world uses value v of
        attribute a; column 0 stands for -1 (none). For vectorised checks of picks and goals."""
        table = np.zeros((4, max(self.attr_values) + 1), dtype=bool)
        for a, values in enumerate(self.world_values):
            table[a, np.asarray(values, dtype=np.int64) + 1] = True
        return table

    def cell_allowed(self) -> np.ndarray:
        """(4, max(channel_values)) bool: entry [c, x] is True when channel c may hold value x on this
        world's views (0 = none is always allowed on the attribute channels)."""
        if self.family == "babyai":  # any value of minigrid's tables; the padding channel holds 0 only
            table = np.zeros((VIEW_CHANNELS, max(self.channel_values)), dtype=bool)
            for c, n in enumerate(self.channel_values):
                table[c, :n] = True
            return table
        table = np.zeros((VIEW_CHANNELS, max(self.channel_values)), dtype=bool)
        table[0, : self.channel_values[0]] = True
        for channel, attr in ((1, 0), (2, 2), (3, 3)):  # color, shade, size channels -> attributes
            table[channel, 0] = True
            table[channel, np.asarray(self.world_values[attr], dtype=np.int64) + 1] = True
        if len(self.world_values[1]) < 2:  # a world with one type shows one object kind only
            table[0, KIND_KEY:] = False
            table[0, KIND_KEY + self.world_values[1][0]] = True
        return table


DEFAULT_SPEC = WorldSpec.of(WorldConfig())  # the paper world: the default where none is given
