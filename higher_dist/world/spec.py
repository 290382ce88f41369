"""The world's encodings, stated once: what every layer that touches observations, missions, actions
or outcomes reads (the Q-network, the generator, replay, the generator's dataset, the wire schema's
limits and the checks on incoming episodes).

Two kinds of knowledge live here:
- module constants: the encodings that are the same on every world (channel layout, kinds, actions,
  outcome codes). Attribute indices are into the *global* tables of `higher_dist.config`, so networks
  have the same input sizes on every world and a checkpoint means the same thing everywhere.
- `WorldSpec`: a small frozen record made from a `WorldConfig` with what a run's world adds (view size,
  episode limit, which attribute values this world uses). Build it with `WorldSpec.of(world_cfg)`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from higher_dist.config import COLORS, SHADES, SIZES, TYPES, WorldConfig
from higher_dist.world import language

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

    @classmethod
    def of(cls, world: WorldConfig) -> "WorldSpec":
        values = tuple(tuple(table.index(v) for v in getattr(world, field))
                       for table, field in zip(ATTR_TABLES, ("colors", "types", "shades", "sizes")))
        return cls(view_size=world.view_size, max_steps=world.max_steps, world_values=values,
                   reward_shaping=world.reward_shaping)

    @property
    def view_shape(self) -> tuple[int, int, int]:
        return (self.view_size, self.view_size, VIEW_CHANNELS)

    @property
    def channel_max(self) -> tuple[int, ...]:
        """Largest value of each view channel (network embedding rows, wire value limits)."""
        return tuple(n - 1 for n in self.channel_values)

    @property
    def attr_max(self) -> tuple[int, ...]:
        return tuple(n - 1 for n in self.attr_values)

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
