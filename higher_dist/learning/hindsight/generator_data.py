"""The instruction generator's dataset and its accuracy measure.

`GeneratorDataset` holds (view, mission) pairs taken from successful episodes only: the view is the
frame that shows the success, the mission the instruction it fulfilled. Each pair also keeps where the
object in front lay seen from the episode's start (`WorldSpec.start_locations`; 0 on levels whose
missions never name a location). It is a bounded ring
buffer (FIFO eviction) with a fixed train/validation split.

The split is decided once per pair, when it arrives, by a seeded hash of its insertion number. So a
pair never moves between the splits (validation accuracy stays an honest held-out measure however
the buffer turns over), the fraction is exactly `val_fraction` in expectation, and the same seed
and insertion order always give the same split (checkpoints resume it unchanged).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from higher_dist.learning.episode import SUCCESS, Episode
from higher_dist.world import language as fetchattr_language
from higher_dist.world.spec import DEFAULT_SPEC, WorldSpec

_ATTR_NAMES = ("color", "type", "shade", "size")
_MASK64 = (1 << 64) - 1


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """A well-mixed 64-bit hash of each uint64 (SplitMix64's finaliser); numpy wraps on overflow."""
    z = x + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def validation_flags(insertion_ids: np.ndarray, seed: int, val_fraction: float) -> np.ndarray:
    """Whether each insertion number belongs to the validation split: a pure function of its inputs."""
    ids = np.asarray(insertion_ids, dtype=np.uint64)
    salted = _splitmix64(np.full(ids.shape, int(seed) & _MASK64, dtype=np.uint64)) ^ ids
    # The top 53 bits as a uniform float in [0, 1).
    u = (_splitmix64(salted) >> np.uint64(11)).astype(np.float64) / float(1 << 53)
    return u < val_fraction


def generator_inputs(spec: WorldSpec, ep: Episode, steps) -> tuple[np.ndarray, np.ndarray]:
    """What the generator reads of the outcomes achieved at `steps` of `ep`: the views that show them
    (`WorldSpec.outcome_view_offset`) and where the object in front lay seen from the start
    (`WorldSpec.start_locations`, reckoned from the episode's frames and actions). Never what was achieved."""
    shown = np.asarray(steps, dtype=np.int64).reshape(-1) + spec.outcome_view_offset
    return ep.frames[shown], spec.start_locations(ep.frames, ep.actions, shown)


class GeneratorDataset:
    def __init__(self, capacity: int, val_fraction: float, seed: int, spec: WorldSpec = DEFAULT_SPEC):
        if capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {capacity}")
        if not 0.0 < val_fraction < 1.0:
            raise ValueError(f"val_fraction: must be in (0, 1), got {val_fraction}")
        self.capacity, self.val_fraction, self.seed = int(capacity), float(val_fraction), int(seed)
        self.views = np.zeros((capacity, *spec.view_shape), np.uint8)
        self.tokens = np.zeros((capacity, spec.mission_len), np.int64)
        self.where = np.zeros(capacity, np.int64)
        self.spec = spec
        self.is_val = np.zeros(capacity, bool)
        self.inserted = 0  # pairs ever added; also the next pair's insertion number
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(self, view: np.ndarray, tokens: np.ndarray, where: int = 0) -> None:
        self.add_many(np.asarray(view)[None], np.asarray(tokens)[None], np.array([where]))

    def add_many(self, views: np.ndarray, tokens: np.ndarray, where: np.ndarray | None = None) -> None:
        """Append pairs in order (with their start locations; None: 0); the oldest ones are overwritten once
        the buffer is full."""
        views, tokens = np.asarray(views), np.asarray(tokens)
        n = views.shape[0]
        where = np.zeros(n, np.int64) if where is None else np.asarray(where, np.int64)
        if views.shape[1:] != self.views.shape[1:] or tokens.shape != (n, self.tokens.shape[1]) or where.shape != (n,):
            raise ValueError(f"pairs: expected views (n,{self.views.shape[1]},{self.views.shape[2]},4), "
                             f"tokens (n,{self.tokens.shape[1]}) and where (n,), got {views.shape}, {tokens.shape} "
                             f"and {where.shape}")
        if n == 0:
            return
        if n > self.capacity:  # only the newest `capacity` pairs would survive anyway
            skip = n - self.capacity
            self.inserted += skip
            views, tokens, where, n = views[skip:], tokens[skip:], where[skip:], self.capacity
        ids = np.arange(self.inserted, self.inserted + n)
        slots = ids % self.capacity
        self.views[slots] = views
        self.tokens[slots] = tokens
        self.where[slots] = where
        self.is_val[slots] = validation_flags(ids, self.seed, self.val_fraction)
        self.inserted += n
        self.size = min(self.capacity, self.size + n)

    def add_episode(self, ep: Episode) -> bool:
        """Keep the pair of a successful, original episode: the view that shows its success (before the
        last step, or after it on a go-to level) and its mission. Anything else is refused (returns False).

        Relabelled copies are refused even though they end in reward 1: their mission was written
        by a relabeller, and training on them would feed the generator its own (or noisy) outputs.
        """
        if ep.outcome != SUCCESS or ep.relabelled or ep.length < 1:
            return False
        views, where = generator_inputs(self.spec, ep, [ep.length - 1])
        self.add(views[0], ep.mission, int(where[0]))
        return True

    def _filled(self) -> np.ndarray:
        """Slots holding pairs, oldest first."""
        if self.size < self.capacity:
            return np.arange(self.size)
        return (np.arange(self.capacity) + self.inserted) % self.capacity

    @property
    def n_val(self) -> int:
        return int(self.is_val[self._filled()].sum())

    @property
    def n_train(self) -> int:
        return self.size - self.n_val

    def sample_train(self, batch_size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A uniform batch (with replacement) of training pairs: (views (b,V,V,4), tokens (b,L), where (b,))."""
        slots = self._filled()
        train = slots[~self.is_val[slots]]
        if train.size == 0:
            raise ValueError("sample_train: the dataset holds no training pairs yet")
        pick = train[rng.integers(0, train.size, size=batch_size)]
        return self.views[pick], self.tokens[pick], self.where[pick]

    def validation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every validation pair currently held, oldest first (copies): views, tokens, where."""
        slots = self._filled()
        val = slots[self.is_val[slots]]
        return self.views[val].copy(), self.tokens[val].copy(), self.where[val].copy()

    def state_dict(self) -> dict[str, Any]:
        slots = self._filled()
        return {"capacity": self.capacity, "val_fraction": self.val_fraction, "seed": self.seed,
                "inserted": self.inserted, "views": self.views[slots].copy(),
                "tokens": self.tokens[slots].copy(), "where": self.where[slots].copy(),
                "is_val": self.is_val[slots].copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if int(state["capacity"]) != self.capacity:
            raise ValueError(f"dataset: checkpoint capacity {state['capacity']} != {self.capacity}")
        self.val_fraction, self.seed = float(state["val_fraction"]), int(state["seed"])
        views, tokens, is_val = state["views"], state["tokens"], state["is_val"]
        n = len(views)
        self.inserted = int(state["inserted"])
        self.size = n
        self.views[:] = 0
        self.tokens[:] = 0
        self.where[:] = 0
        self.is_val[:] = False
        # Put the pairs back at the slots their insertion numbers map to, so that further adds
        # evict them in the same order as before the checkpoint.
        slots = np.arange(self.inserted - n, self.inserted) % self.capacity
        self.views[slots], self.tokens[slots], self.is_val[slots] = views, tokens, is_val
        self.where[slots] = state.get("where", 0)  # a checkpoint that holds no locations: all 0


def semantic_accuracy(pred_tokens: np.ndarray, true_attrs: np.ndarray, language=fetchattr_language) -> dict[str, float]:
    """How often the generated instructions describe the right object, whatever their word order.

    exact: the output describes the true object (`language.satisfies`: on FetchAttr all four attributes
    right; on a BabyAI level colour and type right or unnamed, as the level's own missions may leave
    them); color/type/shade/size: that column right or unnamed (on a BabyAI level the last two columns
    are location and article); an output that does not parse counts as wrong everywhere. parse_rate:
    fraction of outputs that parse. `language`: the world's (WorldSpec.language).
    """
    true_attrs = np.asarray(true_attrs, dtype=np.int64).reshape(-1, 4)
    n = true_attrs.shape[0]
    if n == 0:
        return {"exact": 0.0, **{a: 0.0 for a in _ATTR_NAMES}, "parse_rate": 0.0, "n": 0}
    pred_attrs, ok = language.parse_many(pred_tokens)
    # A column is right when it names the true value or (BabyAI's partial descriptions) leaves it unnamed.
    match = ((pred_attrs == true_attrs) | (pred_attrs == -1)) & ok[:, None]
    out: dict[str, float] = {"exact": float((language.satisfies(pred_attrs, true_attrs) & ok).mean())}
    for j, name in enumerate(_ATTR_NAMES):
        out[name] = float(match[:, j].mean())
    out["parse_rate"] = float(ok.mean())
    out["n"] = n
    return out
