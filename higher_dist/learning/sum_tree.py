"""An array-based binary sum tree: the index structure behind proportional prioritized replay.

Layout: `tree` holds 2 * n_leaves float64 values, the root at index 1, the children of node p at 2p
and 2p + 1, and leaf i at `n_leaves + i` (index 0 is unused). `n_leaves` is the smallest power of two
>= capacity, so every leaf sits at the same depth and a descent is one vector operation per level for
a whole batch. Leaves past `capacity` stay 0 and can therefore never be sampled.

Every internal node is *recomputed* as left + right rather than adjusted by a delta, so there is no
drift from accumulated round-off however many updates are made, and a node is > 0 exactly when one of
its children is > 0: the descent guard below relies on that.

Speed comes from the number of NumPy calls, not from arithmetic (batches are small), so two shortcuts
cut the per-level calls where it is exact to do so:
- sample: the top `_search_depth` levels are resolved at once by a binary search over the prefix sums
  of one level of at most 4096 nodes (one cumsum per batch), then the descent continues per level;
- update: a level whose touched nodes span a short index range is recomputed as one sliced add over
  that range (recomputing an untouched node from its children reproduces its value exactly).
"""
from __future__ import annotations

import numpy as np

_SEARCH_LEVEL_MAX = 12  # a level of 2^12 nodes: its cumsum costs about as much as one descent level
_SLICE_SPAN_MAX = 4096  # recompute a level as one slice when its touched range is at most this wide


class SumTree:
    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f"SumTree capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.n_leaves = 1 << max(0, (self.capacity - 1).bit_length())
        self.depth = self.n_leaves.bit_length() - 1  # levels below the root
        self.tree = np.zeros(2 * self.n_leaves, dtype=np.float64)
        # Largest value ever written; prioritized replay gives new data this priority.
        self.max_priority = 0.0
        self._search_depth = min(self.depth, _SEARCH_LEVEL_MAX)

    def total(self) -> float:
        return float(self.tree[1])

    def get(self, indices: np.ndarray) -> np.ndarray:
        return self.tree[self.n_leaves + np.asarray(indices, dtype=np.int64)]

    def leaves(self) -> np.ndarray:
        """A read-only view of the capacity leaves."""
        view = self.tree[self.n_leaves:self.n_leaves + self.capacity]
        view.flags.writeable = False
        return view

    # ----------------------------------------------------------------------------------- update

    def update(self, indices: np.ndarray, priorities: np.ndarray) -> None:
        """Set leaves `indices` to `priorities`; with a repeated index the last one in the batch wins."""
        idx = np.asarray(indices, dtype=np.int64).ravel()
        values = np.broadcast_to(np.asarray(priorities, dtype=np.float64), idx.shape)
        if idx.size == 0:
            return
        if idx.min() < 0 or idx.max() >= self.capacity:
            raise IndexError(f"SumTree leaf index out of range [0, {self.capacity})")
        _check_priorities(values)
        if idx.size > 1 and np.all(np.diff(idx) == 1):
            self._write_run(int(idx[0]), values)  # consecutive leaves: the cheap sliced path
            return
        if idx.size > 1:
            # NumPy does not promise which of several writes to one element wins, so keep only the
            # last occurrence of each index explicitly: a stable sort keeps batch order within ties.
            order = np.argsort(idx, kind="stable")
            idx = idx[order]
            values = values[order]
            last = np.empty(idx.size, dtype=bool)
            np.not_equal(idx[:-1], idx[1:], out=last[:-1])
            last[-1] = True
            idx = idx[last]
            values = values[last]
        tree = self.tree
        nodes = idx + self.n_leaves  # sorted, so each level's range is [nodes[0], nodes[-1]]
        tree[nodes] = values
        self.max_priority = max(self.max_priority, float(values.max()))
        for level in range(self.depth):
            nodes >>= 1
            lo, hi = int(nodes[0]), int(nodes[-1])
            if hi - lo < _SLICE_SPAN_MAX:
                self._recompute_range(lo, hi, self.depth - level)
                return
            # Duplicated parents are harmless (they all write the same sum): no de-duplication.
            left = nodes << 1
            tree[nodes] = tree[left] + tree[left + 1]

    def update_run(self, first: int, priorities: np.ndarray) -> None:
        """Set the consecutive leaves first, first+1, ... to `priorities` (no wrap-around).

        The common case for a replay, which writes an episode into consecutive slots: every level of
        ancestors is then a contiguous run too, so each level costs one sliced add instead of gathers.
        """
        values = np.asarray(priorities, dtype=np.float64).ravel()
        if values.size == 0:
            return
        if first < 0 or first + values.size > self.capacity:
            raise IndexError(f"SumTree run [{first}, {first + values.size}) outside [0, {self.capacity})")
        _check_priorities(values)
        self._write_run(first, values)

    def restore_run(self, first: int, values: np.ndarray) -> None:
        """Put back leaves first, first+1, ... as they were read before a write (a replay's undo of an
        insert that failed part-way); the caller puts back `max_priority` too."""
        self._write_run(first, np.asarray(values, dtype=np.float64))

    def _write_run(self, first: int, values: np.ndarray) -> None:
        lo = first + self.n_leaves
        self.tree[lo:lo + values.size] = values
        self.max_priority = max(self.max_priority, float(values.max()))
        self._recompute_range(lo >> 1, (lo + values.size - 1) >> 1, self.depth)

    def _recompute_range(self, lo: int, hi: int, levels: int) -> None:
        """Recompute nodes lo..hi (inclusive, one level) and the ranges above them, `levels` levels."""
        tree = self.tree
        for _ in range(levels):
            np.add(tree[2 * lo:2 * hi + 2:2], tree[2 * lo + 1:2 * hi + 2:2], out=tree[lo:hi + 1])
            lo >>= 1
            hi >>= 1

    # ----------------------------------------------------------------------------------- sample

    def sample_stratified(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n leaf indices, one value drawn in each of n equal slices of the total mass: a batch spreads
        over the buffer while each draw keeps probability p_i / total overall."""
        values = rng.random(n)
        values += np.arange(n)
        values *= self.total() / n
        return self.sample(values)

    def sample(self, values: np.ndarray) -> np.ndarray:
        """Leaf indices whose prefix-sum interval contains each value (values in [0, total)).

        A leaf of zero priority is never returned while total() > 0, even for a value at or beyond the
        total or a round-off mismatch between a node and its children.
        """
        if not self.tree[1] > 0:
            raise ValueError("cannot sample from a SumTree whose total priority is 0")
        values = np.asarray(values, dtype=np.float64).ravel()
        tree = self.tree
        # Top levels at once: the node of level L whose prefix-sum interval holds each value. With
        # side="right" a value equal to a prefix sum skips past zero-mass nodes; values at or past the
        # level's total are clamped to its last node (the guard below catches a zero one).
        width = 1 << self._search_depth
        level = tree[width:2 * width]
        prefix = np.cumsum(level)
        slot = np.searchsorted(prefix, values, side="right")
        np.minimum(slot, width - 1, out=slot)
        remaining = values - (prefix[slot] - level[slot])
        np.maximum(remaining, 0.0, out=remaining)  # round-off could leave it a hair below 0
        nodes = slot + width
        for _ in range(self.depth - self._search_depth):
            nodes <<= 1  # left child
            left = tree[nodes]
            go_right = remaining >= left
            remaining -= left * go_right
            nodes += go_right
        # Round-off can send a value into a zero-priority subtree (a value at the total, or a node sum
        # that rounds above its children's). That is rare: redo those with the guarded descent instead
        # of paying for the guard on every sample.
        bad = tree[nodes] <= 0
        if bad.any():
            nodes[bad] = self._guarded_descent(values[bad])
        return nodes - self.n_leaves

    def _guarded_descent(self, values: np.ndarray) -> np.ndarray:
        # Go right when the value passes the left sum and the right subtree has mass, or when the left
        # subtree has none; since a positive node has a positive child, this ends on a positive leaf.
        tree = self.tree
        remaining = values.copy()
        nodes = np.ones(remaining.size, dtype=np.int64)
        for _ in range(self.depth):
            left, right = tree[2 * nodes], tree[2 * nodes + 1]
            go_right = ((remaining >= left) & (right > 0)) | (left <= 0)
            remaining = np.where(go_right, remaining - left, remaining)
            nodes = 2 * nodes + go_right
        return nodes

    # ------------------------------------------------------------------------------- checkpoint

    def state_dict(self) -> dict:
        return {"capacity": self.capacity, "tree": self.tree.copy(), "max_priority": self.max_priority}

    def load_state_dict(self, state: dict) -> None:
        if int(state["capacity"]) != self.capacity:
            raise ValueError(f"SumTree capacity mismatch: state has {state['capacity']}, tree has {self.capacity}")
        tree = np.asarray(state["tree"], dtype=np.float64)
        if tree.shape != self.tree.shape:
            raise ValueError(f"SumTree state has shape {tree.shape}, expected {self.tree.shape}")
        self.tree[:] = tree
        self.max_priority = float(state["max_priority"])


def _check_priorities(values: np.ndarray) -> None:
    if not (np.isfinite(values).all() and values.min() >= 0):
        raise ValueError("SumTree priorities must be finite and >= 0")
