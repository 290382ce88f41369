"""The objects of a FetchAttr world and the fixed train / held-out split of them.

An object is four attribute indices `(color, type, shade, size)` into the *global* tables of
`higher_dist.config` (COLORS, TYPES, SHADES, SIZES). A world may use a subset of each table; the
indices stay global so that networks see the same value ranges on every world.
"""
from __future__ import annotations

import itertools

import numpy as np

from higher_dist.config import COLORS, SHADES, SIZES, TYPES, ConfigError, WorldConfig, validate_world

ATTR_NAMES = ("color", "type", "shade", "size")
GLOBAL_TABLES = (COLORS, TYPES, SHADES, SIZES)
COLOR, TYPE, SHADE, SIZE = range(4)
_CONFIG_FIELDS = ("colors", "types", "shades", "sizes")  # WorldConfig fields, in attribute order

# Seeded permutations tried before the split is declared impossible. The paper world accepts the
# first try almost always and the small world one try in three, so this bound is never reached by a
# split that exists with non-negligible probability.
_SPLIT_TRIES = 10_000


class ObjectSpace:
    """All objects of a world, the fixed train / held-out split and the values of each attribute.

    The split is found by seeded rejection sampling: permute the objects with `split_seed`, hold out
    the last `heldout_count`, and accept when every attribute value of the world occurs in both sets.
    `heldout_count == 0` means "no held-out set": every object is a training object.
    """

    def __init__(self, cfg: WorldConfig):
        validate_world(cfg)
        self.cfg = cfg
        self._values = tuple(
            np.array([table.index(v) for v in getattr(cfg, field)], dtype=np.int8)
            for table, field in zip(GLOBAL_TABLES, _CONFIG_FIELDS)
        )
        self.all_objects = np.array(list(itertools.product(*self._values)), dtype=np.int8)
        self.train_objects, self.heldout_objects = self._split()
        for array in (self.all_objects, self.train_objects, self.heldout_objects):
            array.flags.writeable = False  # shared by every env and relabeler: never edited

    def values(self, attr: int) -> np.ndarray:
        """Global indices of the values this world uses for attribute `attr` (0 color .. 3 size)."""
        return self._values[attr]

    def objects(self, goal_set: str) -> np.ndarray:
        """The objects episodes draw from: "train" or "heldout"."""
        if goal_set == "train":
            return self.train_objects
        if goal_set == "heldout":
            if len(self.heldout_objects) == 0:
                raise ValueError("goal_set 'heldout': this world has heldout_count=0, no held-out objects")
            return self.heldout_objects
        raise ValueError(f"goal_set: must be 'train' or 'heldout', got {goal_set!r}")

    def _covers_every_value(self, subset: np.ndarray) -> bool:
        return all(len(np.unique(subset[:, attr])) == len(self._values[attr]) for attr in range(4))

    def _split(self) -> tuple[np.ndarray, np.ndarray]:
        n_all, n_held = len(self.all_objects), self.cfg.heldout_count
        if n_held == 0:
            return self.all_objects.copy(), self.all_objects[:0].copy()
        widest = max(len(v) for v in self._values)
        if n_held < widest or n_all - n_held < widest:
            raise ConfigError(
                f"world.heldout_count: {n_held} held-out and {n_all - n_held} training objects cannot "
                f"both contain all {widest} values of the widest attribute")
        rng = np.random.default_rng(self.cfg.split_seed)
        for _ in range(_SPLIT_TRIES):
            order = rng.permutation(n_all)
            # Sorting keeps each set in the lexicographic order of all_objects: stable and readable.
            train = self.all_objects[np.sort(order[: n_all - n_held])]
            heldout = self.all_objects[np.sort(order[n_all - n_held:])]
            if self._covers_every_value(train) and self._covers_every_value(heldout):
                return train, heldout
        raise ConfigError(
            f"world.heldout_count: found no split of {n_all} objects into {n_all - n_held} training and "
            f"{n_held} held-out ones with every attribute value in both, after {_SPLIT_TRIES} tries")

    def names(self, attrs) -> str:
        """Readable form of one object, e.g. 'large very_dark green key'."""
        color, kind, shade, size = (int(a) for a in attrs)
        return f"{SIZES[size]} {SHADES[shade]} {COLORS[color]} {TYPES[kind]}"
