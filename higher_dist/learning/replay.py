"""Proportional prioritized replay over whole episodes, with n-step targets precomputed at insert.

Storage is one ring of `capacity` slots. An episode of T actions takes T+1 consecutive slots, one per
frame; slot t holds frame t, action t and the n-step target of transition t, and the last slot holds
the final frame only (never sampled: priority 0). Frames are stored once, so frame stacks and next
states are gathered at sample time instead of being duplicated k or n times.

Bytes per slot: frame V*V*4 = 196 (V=7) + action 1 + n-step return 4 + discount 4 + next offset 1
+ episode record 4 + generation 8 = 218, plus the sum tree (16 bytes per power-of-two leaf, so 16-32
per slot) and per-episode records (start 8, slots 4, origin 1, mission 2*L=20: 33 bytes per episode,
at most one per 2 slots): about 250-270 bytes per slot in the worst case, ~0.27 GB for 1M slots.

Eviction is FIFO by whole episodes: writing a new episode over the oldest one removes all of the
old episode (its remaining slots get priority 0 and are marked free), so a frame stack or an n-step
next state can never mix two episodes.

Frame stacks are ordered oldest first, current frame last: obs[:, k-1] is frame t. Frames before the
episode's start are replaced by the episode's first frame (as if the agent had looked at its first
view k-1 times before acting), which keeps every stack inside one episode and needs no "empty"
frame that the world never produces. The actor side must build its stacks the same way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from higher_dist.config import ReplayConfig
from higher_dist.learning.episode import OUTCOME_NAMES, Episode
from higher_dist.learning.sum_tree import SumTree

__all__ = ["PrioritizedReplay", "SumTree", "TransitionBatch", "ORIGINS"]

# Composition keys; an episode's origin code is its index here.
ORIGINS = (*OUTCOME_NAMES, "relabelled")
_MAX_TOKEN = np.iinfo(np.int16).max  # missions are stored as int16 word ids


@dataclass
class TransitionBatch:
    indices: np.ndarray  # (B,) int64 slots, for update_priorities
    generations: np.ndarray  # (B,) int64 write serials of those slots: stale updates are ignored
    obs: np.ndarray  # (B, k, V, V, 4) uint8, oldest frame first
    mission: np.ndarray  # (B, L) int64
    action: np.ndarray  # (B,) int64
    reward: np.ndarray  # (B,) float32 n-step discounted return
    discount: np.ndarray  # (B,) float32 gamma^m, or 0 when the n steps reach a terminal pick
    next_obs: np.ndarray  # (B, k, V, V, 4) uint8, the stack at step t+m
    weights: np.ndarray  # (B,) float32 importance weights, max 1

    def __len__(self) -> int:
        return int(self.indices.shape[0])


class PrioritizedReplay:
    def __init__(self, cfg: ReplayConfig, frame_stack: int, n_step: int, gamma: float,
                 view_size: int = 7, mission_len: int = 10, seed: int = 0):
        if cfg.capacity < 2:
            raise ValueError(f"replay capacity must be >= 2 slots, got {cfg.capacity}")
        if frame_stack < 1:
            raise ValueError(f"frame_stack must be >= 1, got {frame_stack}")
        if not 1 <= n_step <= 255:  # next-slot offsets are stored as uint8
            raise ValueError(f"n_step must be in [1, 255], got {n_step}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        self.cfg = cfg
        self.capacity = int(cfg.capacity)
        self.frame_stack = int(frame_stack)
        self.n_step = int(n_step)
        self.gamma = float(gamma)
        self.view_size = int(view_size)
        self.mission_len = int(mission_len)
        c, v = self.capacity, self.view_size

        # Per slot.
        self._frames = np.zeros((c, v, v, 4), dtype=np.uint8)
        self._action = np.zeros(c, dtype=np.uint8)
        self._return = np.zeros(c, dtype=np.float32)
        self._discount = np.zeros(c, dtype=np.float32)
        self._next_offset = np.zeros(c, dtype=np.uint8)  # m; 0 marks a final frame (no transition)
        self._episode = np.full(c, -1, dtype=np.int32)  # episode record, -1 = free slot
        self._generation = np.full(c, -1, dtype=np.int64)  # serial of the write that filled the slot

        # Per episode record: a ring indexed by episode serial % n_records. Every episode takes >= 2
        # slots, so at most capacity // 2 are alive at once and live serials never collide.
        self._n_records = c // 2 + 1
        self._ep_start = np.zeros(self._n_records, dtype=np.int64)
        self._ep_slots = np.zeros(self._n_records, dtype=np.int32)
        self._ep_origin = np.zeros(self._n_records, dtype=np.int8)
        self._ep_mission = np.zeros((self._n_records, self.mission_len), dtype=np.int16)

        self._tree = SumTree(c)
        self._rng = np.random.default_rng(seed)
        self._cursor = 0  # next slot to write
        self._writes = 0  # slots ever written: the next generation number
        self._first_live = 0  # serial of the oldest live episode
        self._next_serial = 0  # serial of the next episode
        self._size = 0  # sampleable transitions
        self._counts = np.zeros(len(ORIGINS), dtype=np.int64)
        self._transitions_added = 0
        self._stack_back = np.arange(self.frame_stack - 1, -1, -1, dtype=np.int64)  # k-1 .. 0

    # ----------------------------------------------------------------------------------- insert

    def add_episode(self, ep: Episode) -> None:
        """Store an episode's T transitions (T+1 slots), evicting the oldest episodes as needed."""
        steps = ep.length
        n_slots = steps + 1
        v = self.view_size
        if steps < 1:
            raise ValueError("an episode needs at least one action")
        if n_slots > self.capacity:
            raise ValueError(f"an episode of {steps} steps needs {n_slots} slots, more than the "
                             f"replay capacity {self.capacity}")
        if ep.frames.shape != (n_slots, v, v, 4):
            raise ValueError(f"episode frames have shape {ep.frames.shape}, expected {(n_slots, v, v, 4)}")
        if ep.rewards.shape != (steps,):
            raise ValueError(f"episode rewards have shape {ep.rewards.shape}, expected ({steps},)")
        mission = np.asarray(ep.mission)
        if mission.shape != (self.mission_len,) or mission.min() < 0 or mission.max() > _MAX_TOKEN:
            raise ValueError(f"episode mission must be ({self.mission_len},) word ids in [0, {_MAX_TOKEN}]")

        returns, discounts, offsets = self._n_step_targets(ep.rewards, ep.terminated)
        actions = np.zeros(n_slots, dtype=np.uint8)
        actions[:steps] = ep.actions
        priorities = np.full(n_slots, max(self._tree.max_priority, 1.0))
        priorities[-1] = 0.0  # the final frame is a next state only

        self._evict_overlapping(n_slots)
        start = self._cursor
        record = self._next_serial % self._n_records
        for slot, lo, hi in self._runs(start, n_slots):
            end = slot + hi - lo
            self._frames[slot:end] = ep.frames[lo:hi]
            self._action[slot:end] = actions[lo:hi]
            self._return[slot:end] = returns[lo:hi]
            self._discount[slot:end] = discounts[lo:hi]
            self._next_offset[slot:end] = offsets[lo:hi]
            self._episode[slot:end] = record
            self._generation[slot:end] = np.arange(self._writes + lo, self._writes + hi)
            self._tree.update_run(slot, priorities[lo:hi])

        origin = ORIGINS.index(ep.origin)
        self._ep_start[record] = start
        self._ep_slots[record] = n_slots
        self._ep_origin[record] = origin
        self._ep_mission[record] = mission
        self._next_serial += 1
        self._cursor = (start + n_slots) % self.capacity
        self._writes += n_slots
        self._counts[origin] += steps
        self._size += steps
        self._transitions_added += steps

    def _n_step_targets(self, rewards: np.ndarray, terminated: bool):
        """Per slot: n-step return, discount and offset to the next state (the final slot gets 0s).

        Transition t looks m = min(n, T - t) steps ahead: R = sum_{i<m} gamma^i r_{t+i}, next state
        frame t+m, discount gamma^m, or 0 when t+m == T and a pick ended the episode. A time-out is a
        truncation, so it bootstraps from the final frame.
        """
        steps, n = rewards.shape[0], self.n_step
        padded = np.zeros(steps + n, dtype=np.float64)  # zeros past the end cut sums short at m < n
        padded[:steps] = rewards
        returns = np.zeros(steps + 1, dtype=np.float64)
        for i in range(n):
            returns[:steps] += self.gamma ** i * padded[i:i + steps]
        m = np.minimum(n, steps - np.arange(steps))
        discounts = np.zeros(steps + 1, dtype=np.float64)
        discounts[:steps] = self.gamma ** m
        if terminated:
            discounts[max(0, steps - n):steps] = 0.0  # exactly the t with t + m == T
        offsets = np.zeros(steps + 1, dtype=np.uint8)
        offsets[:steps] = m
        return returns.astype(np.float32), discounts.astype(np.float32), offsets

    def _runs(self, start: int, count: int):
        """(slot, lo, hi) pieces of `count` slots from `start`: one, or two when the ring wraps."""
        first = min(count, self.capacity - start)
        yield start, 0, first
        if first < count:
            yield 0, first, count

    def _evict_overlapping(self, n_slots: int) -> None:
        # Live episodes lie in ring order from the oldest one's start up to the cursor, so the ones
        # the next n_slots slots reach are the oldest whose start is < n_slots ahead of the cursor.
        while self._first_live < self._next_serial:
            record = self._first_live % self._n_records
            start = int(self._ep_start[record])
            if (start - self._cursor) % self.capacity >= n_slots:
                break
            slots = int(self._ep_slots[record])
            for slot, lo, hi in self._runs(start, slots):
                self._tree.update_run(slot, np.zeros(hi - lo))
                self._episode[slot:slot + hi - lo] = -1
            self._counts[self._ep_origin[record]] -= slots - 1
            self._size -= slots - 1
            self._first_live += 1

    # ----------------------------------------------------------------------------------- sample

    def sample(self, batch_size: int, beta: float, rng: np.random.Generator | None = None) -> TransitionBatch:
        """A prioritized batch; `rng` defaults to the replay's own generator."""
        if self._size == 0:
            raise ValueError("the replay holds no transitions to sample")
        rng = self._rng if rng is None else rng
        total = self._tree.total()
        # Stratified: one value per equal slice of the total mass, which spreads a batch over the
        # buffer while each draw keeps probability p_i / total overall.
        values = (np.arange(batch_size) + rng.random(batch_size)) * (total / batch_size)
        slots = self._tree.sample(values)
        probs = self._tree.tree[self._tree.n_leaves + slots] / total
        weights = (self._size * probs) ** (-beta)
        weights /= weights.max()

        episode = self._episode[slots]
        step = (slots - self._ep_start[episode]) % self.capacity  # position t inside the episode
        offset = self._next_offset[slots]
        next_slots = slots + offset
        next_step = step + offset
        if self.frame_stack == 1:
            stacks = np.stack([slots, next_slots], axis=1)
        else:
            back = self._stack_back
            # Clamp how far back each stack reaches at the episode's first frame.
            stacks = np.concatenate([slots[:, None] - np.minimum(back, step[:, None]),
                                     next_slots[:, None] - np.minimum(back, next_step[:, None])], axis=1)
        frames = self._frames[stacks % self.capacity]  # (B, 2k, V, V, 4), one gather for both
        k = self.frame_stack
        return TransitionBatch(
            indices=slots,
            generations=self._generation[slots],
            obs=np.ascontiguousarray(frames[:, :k]),
            mission=self._ep_mission[episode].astype(np.int64),
            action=self._action[slots].astype(np.int64),
            reward=self._return[slots],
            discount=self._discount[slots],
            next_obs=np.ascontiguousarray(frames[:, k:]),
            weights=weights.astype(np.float32),
        )

    def update_priorities(self, indices: np.ndarray, priorities: np.ndarray,
                          generations: np.ndarray | None = None) -> int:
        """Set new priorities from raw |TD| errors; returns how many were applied.

        Updates for slots that no longer hold a sampleable transition are dropped, and with
        `generations` (from the batch) so are those for slots rewritten since sampling: in a
        distributed learner the replay keeps filling while a batch is in flight.
        """
        idx = np.asarray(indices, dtype=np.int64).ravel()
        raw = np.abs(np.asarray(priorities, dtype=np.float64).ravel())
        if raw.shape != idx.shape:
            raise ValueError(f"{idx.size} indices but {raw.size} priorities")
        if not np.isfinite(raw).all():
            raise ValueError("priorities must be finite")
        if idx.size and (idx.min() < 0 or idx.max() >= self.capacity):
            raise IndexError(f"replay slot out of range [0, {self.capacity})")
        keep = (self._episode[idx] >= 0) & (self._next_offset[idx] > 0)
        if generations is not None:
            keep &= self._generation[idx] == np.asarray(generations, dtype=np.int64).ravel()
        if not keep.all():
            idx, raw = idx[keep], raw[keep]
        self._tree.update(idx, (raw + self.cfg.priority_eps) ** self.cfg.alpha)
        return int(idx.size)

    # ------------------------------------------------------------------------------- inspection

    def __len__(self) -> int:
        return self._size

    @property
    def transitions_added(self) -> int:
        """Transitions ever inserted (for a samples-per-insert rate limiter)."""
        return self._transitions_added

    def composition(self) -> dict[str, int]:
        """Sampleable transitions held, by the origin of their episode."""
        return {name: int(count) for name, count in zip(ORIGINS, self._counts)}

    def beta_at(self, frames: int) -> float:
        """Importance-sampling exponent annealed linearly from beta_start to beta_end over beta_frames."""
        c = self.cfg
        if c.beta_frames <= 0:
            return float(c.beta_end)
        frac = min(1.0, max(0.0, frames / c.beta_frames))
        return float(c.beta_start + frac * (c.beta_end - c.beta_start))

    # ------------------------------------------------------------------------------- checkpoint

    _ARRAYS = ("_frames", "_action", "_return", "_discount", "_next_offset", "_episode", "_generation",
               "_ep_start", "_ep_slots", "_ep_origin", "_ep_mission", "_counts")
    _INTS = ("_cursor", "_writes", "_first_live", "_next_serial", "_size", "_transitions_added")

    def state_dict(self) -> dict:
        """A flat dict of numpy arrays and Python numbers (np.savez-able without pickle)."""
        state: dict = {"capacity": self.capacity, "n_step": self.n_step, "gamma": self.gamma,
                       "view_size": self.view_size, "mission_len": self.mission_len}
        for name in self._ARRAYS:
            state[name.lstrip("_")] = getattr(self, name).copy()
        for name in self._INTS:
            state[name.lstrip("_")] = int(getattr(self, name))
        tree = self._tree.state_dict()
        state["tree"] = tree["tree"]
        state["tree_max_priority"] = tree["max_priority"]
        state["rng_state"] = _pcg64_to_array(self._rng)
        return state

    def load_state_dict(self, state: dict) -> None:
        for key in ("capacity", "n_step", "view_size", "mission_len"):
            if int(state[key]) != getattr(self, key):
                raise ValueError(f"replay state has {key}={state[key]}, this replay has {getattr(self, key)}")
        if float(state["gamma"]) != self.gamma:  # stored returns were computed with it
            raise ValueError(f"replay state has gamma={state['gamma']}, this replay has {self.gamma}")
        for name in self._ARRAYS:
            target = getattr(self, name)
            value = np.asarray(state[name.lstrip("_")])
            if value.shape != target.shape:
                raise ValueError(f"replay state {name.lstrip('_')} has shape {value.shape}, expected {target.shape}")
            target[...] = value
        for name in self._INTS:
            setattr(self, name, int(state[name.lstrip("_")]))
        self._tree.load_state_dict({"capacity": self.capacity, "tree": state["tree"],
                                    "max_priority": state["tree_max_priority"]})
        _pcg64_from_array(self._rng, state["rng_state"])


def _pcg64_to_array(rng: np.random.Generator) -> np.ndarray:
    """The generator's PCG64 state as 6 uint64 words, so a checkpoint needs no pickled dict."""
    s = rng.bit_generator.state
    if s["bit_generator"] != "PCG64":
        raise ValueError(f"cannot store a {s['bit_generator']} generator state")
    mask = (1 << 64) - 1
    state, inc = s["state"]["state"], s["state"]["inc"]
    return np.array([state >> 64, state & mask, inc >> 64, inc & mask, s["has_uint32"], s["uinteger"]],
                    dtype=np.uint64)


def _pcg64_from_array(rng: np.random.Generator, words: np.ndarray) -> None:
    w = [int(x) for x in np.asarray(words, dtype=np.uint64)]
    rng.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
        "has_uint32": w[4], "uinteger": w[5],
    }
