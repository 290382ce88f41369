"""Proportional prioritized replay over whole episodes, with n-step targets precomputed at insert.

Storage is one ring of `capacity` slots. An episode of T actions takes T+1 consecutive slots, one per
frame; slot t holds frame t, action t and the n-step target of transition t, and the last slot holds
the final frame only (never sampled: priority 0). Frames are stored once, so frame stacks and next
states are gathered at sample time instead of being duplicated k or n times.

Bytes per slot: frame V*V*4 = 196 (V=7) + action 1 + n-step return 4 + discount 4 + next offset 1
+ stack history 1 + episode record 4 + generation 8 = 219, plus the sum tree (16 bytes per
power-of-two leaf: 16-32 per slot) and the per-episode records (start 8, slots 4, origin 1, mission
2*L = 20: 33 bytes, sized for the worst case of one episode per 2 slots, ~17 per slot): 250-270 bytes
per slot, about 0.25 GB for 1M slots (np.zeros pages are only committed when first written).

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
from higher_dist.learning.episode_sampling import EpisodeSampling, SequenceBatch
from higher_dist.learning.exploration import linear_schedule
from higher_dist.learning.seeds import rng_state_from_array, rng_state_to_array
from higher_dist.learning.sum_tree import SumTree
from higher_dist.world.spec import DEFAULT_SPEC, WorldSpec

__all__ = ["PrioritizedReplay", "SumTree", "TransitionBatch", "SequenceBatch", "ORIGINS"]

# Composition keys; an episode's origin code is its index here.
ORIGINS = (*OUTCOME_NAMES, "relabelled")
_MAX_TOKEN = np.iinfo(np.int16).max  # missions are stored as int16 word ids
# The state an insert writes: per slot, and per episode record.
_SLOT_ARRAYS = ("_frames", "_action", "_return", "_discount", "_next_offset", "_history", "_episode", "_generation")
_RECORD_ARRAYS = ("_ep_start", "_ep_slots", "_ep_origin", "_ep_mission")


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

    def priority_update(self, priorities: np.ndarray) -> tuple:
        """(slots, priorities, generations) for `update_priorities`: every transition of the batch."""
        return self.indices, priorities, self.generations


class PrioritizedReplay(EpisodeSampling):  # sample_episodes: whole episodes, for the recurrent core
    def __init__(self, cfg: ReplayConfig, frame_stack: int, n_step: int, gamma: float,
                 spec: WorldSpec = DEFAULT_SPEC, seed: int = 0):
        if cfg.capacity < 2:
            raise ValueError(f"replay capacity must be >= 2 slots, got {cfg.capacity}")
        if not 1 <= frame_stack <= 256:  # stack reach is stored as uint8
            raise ValueError(f"frame_stack must be in [1, 256], got {frame_stack}")
        if not 1 <= n_step <= 255:  # next-slot offsets are stored as uint8
            raise ValueError(f"n_step must be in [1, 255], got {n_step}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        self.cfg = cfg
        self.capacity = int(cfg.capacity)
        self.frame_stack = int(frame_stack)
        self.n_step = int(n_step)
        self.gamma = float(gamma)
        self.spec = spec
        self.view_size = int(spec.view_size)
        self.mission_len = int(spec.mission_len)
        c, v = self.capacity, self.view_size

        # Per slot.
        self._frames = np.zeros((c, v, v, 4), dtype=np.uint8)
        self._action = np.zeros(c, dtype=np.uint8)
        self._return = np.zeros(c, dtype=np.float32)
        self._discount = np.zeros(c, dtype=np.float32)
        self._next_offset = np.zeros(c, dtype=np.uint8)  # m; 0 marks a final frame (no transition)
        self._history = np.zeros(c, dtype=np.uint8)  # min(t, 255): earlier frames a stack may reach
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
        self._stack_back = np.arange(self.frame_stack - 1, -1, -1, dtype=np.int64)  # k-1 .. 0
        self._gamma_pow = self.gamma ** np.arange(self.n_step + 1, dtype=np.float64)

    # ----------------------------------------------------------------------------------- insert

    def add_episode(self, ep: Episode) -> None:
        """Store an episode's T transitions (T+1 slots), evicting the oldest episodes as needed."""
        self.add_episodes([ep])

    def add_episodes(self, episodes: list[Episode]) -> None:
        """Store a batch of episodes, all or none: every episode is checked and prepared before anything is
        written, and a write that fails part-way puts the replay back exactly as it was (slots, records, sum
        tree, counters) before the error goes on: no half-stored batch is left for a checkpoint."""
        prepared = [self._prepare(ep) for ep in episodes]
        undo = _InsertUndo(self)
        try:
            for p in prepared:
                self._write(p, undo)
        except BaseException:
            undo.roll_back()
            raise

    def _prepare(self, ep: Episode) -> tuple:
        """An episode checked and turned into what `_write` stores; nothing in the replay changes."""
        steps, v = ep.length, self.view_size
        n_slots = steps + 1
        if steps < 1:
            raise ValueError("an episode needs at least one action")
        if n_slots > self.capacity:
            raise ValueError(f"an episode of {steps} steps needs {n_slots} slots, more than the "
                             f"replay capacity {self.capacity}")
        if ep.frames.shape != (n_slots, v, v, 4):
            raise ValueError(f"episode frames have shape {ep.frames.shape}, expected {(n_slots, v, v, 4)}")
        self.spec.check_cells(ep.frames, "episode frames")
        if ep.rewards.shape != (steps,):
            raise ValueError(f"episode rewards have shape {ep.rewards.shape}, expected ({steps},)")
        mission = np.asarray(ep.mission)
        if mission.shape != (self.mission_len,) or mission.min() < 0 or mission.max() > _MAX_TOKEN:
            raise ValueError(f"episode mission must be ({self.mission_len},) word ids in [0, {_MAX_TOKEN}]")
        # A time-out is a truncation (bootstrapped) unless the run stores it as the paper's code did.
        terminal = ep.terminated or self.cfg.timeouts_terminal
        returns, discounts, offsets = self._n_step_targets(ep.rewards, terminal)
        actions = np.zeros(n_slots, dtype=np.uint8)
        actions[:steps] = ep.actions
        return steps, ep.frames, actions, returns, discounts, offsets, mission, ORIGINS.index(ep.origin)

    def _write(self, prepared: tuple, undo: _InsertUndo) -> None:
        steps, frames, actions, returns, discounts, offsets, mission, origin = prepared
        n_slots = steps + 1
        span = self._evict_for(n_slots)
        start, record = self._cursor, self._next_serial % self._n_records
        undo.save(start, span, record)
        for slot, lo, hi in self._runs(start, n_slots):
            end = slot + hi - lo
            self._frames[slot:end] = frames[lo:hi]
            self._action[slot:end] = actions[lo:hi]
            self._return[slot:end] = returns[lo:hi]
            self._discount[slot:end] = discounts[lo:hi]
            self._next_offset[slot:end] = offsets[lo:hi]
            self._history[slot:end] = np.minimum(np.arange(lo, hi), 255)
            self._episode[slot:end] = record
            self._generation[slot:end] = np.arange(self._writes + lo, self._writes + hi)
        if span > n_slots:  # leftovers of evicted episodes become free slots
            for slot, lo, hi in self._runs((start + n_slots) % self.capacity, span - n_slots):
                self._episode[slot:slot + hi - lo] = -1
        # One tree write covers the new transitions (max priority), the final frame (0, a next state
        # only) and the leftovers of evicted episodes (0, so no stack can mix episodes).
        priorities = np.zeros(span)
        priorities[:steps] = max(self._tree.max_priority, 1.0)
        for slot, lo, hi in self._runs(start, span):
            self._tree.update_run(slot, priorities[lo:hi])
        self._ep_start[record] = start
        self._ep_slots[record] = n_slots
        self._ep_origin[record] = origin
        self._ep_mission[record] = mission
        self._next_serial += 1
        self._cursor = (start + n_slots) % self.capacity
        self._writes += n_slots
        self._counts[origin] += steps
        self._size += steps

    def _n_step_targets(self, rewards: np.ndarray, terminated: bool):
        """Per slot: n-step return, discount and offset to the next state (the final slot gets 0s).

        Transition t looks m = min(n, T - t) steps ahead: R = sum_{i<m} gamma^i r_{t+i}, next state
        frame t+m, discount gamma^m, or 0 when t+m == T and a pick ended the episode. A time-out is a
        truncation, so it bootstraps from the final frame.
        """
        steps, n = rewards.shape[0], self.n_step
        padded = np.zeros(steps + n, dtype=np.float64)  # zeros past the end cut sums short at m < n
        padded[:steps] = rewards
        # Sliding dot product with (1, gamma, ..., gamma^(n-1)); the (T+1)th entry sums only padding.
        returns = np.correlate(padded, self._gamma_pow[:n], "valid")
        m = np.minimum(n, steps - np.arange(steps + 1))  # 0 for the final slot
        discounts = self._gamma_pow[m]
        discounts[-1] = 0.0
        if terminated:
            discounts[max(0, steps - n):] = 0.0  # exactly the t with t + m == T
        return returns.astype(np.float32), discounts.astype(np.float32), m.astype(np.uint8)

    def _runs(self, start: int, count: int):
        """(slot, lo, hi) pieces of `count` slots from `start`: one, or two when the ring wraps."""
        first = min(count, self.capacity - start)
        yield start, 0, first
        if first < count:
            yield 0, first, count

    def _evict_for(self, n_slots: int) -> int:
        """Drop the episodes the next n_slots slots reach; returns how many slots from the cursor
        must be rewritten: n_slots, or more when an evicted episode extends past them."""
        # Live episodes lie in ring order from the oldest one's start up to the cursor, so the ones
        # reached are the oldest whose start is less than n_slots ahead of the cursor.
        span = n_slots
        while self._first_live < self._next_serial:
            record = self._first_live % self._n_records
            ahead = (int(self._ep_start[record]) - self._cursor) % self.capacity
            if ahead >= n_slots:
                break
            slots = int(self._ep_slots[record])
            span = max(span, ahead + slots)
            self._counts[self._ep_origin[record]] -= slots - 1
            self._size -= slots - 1
            self._first_live += 1
        return span

    # ----------------------------------------------------------------------------------- sample

    def sample(self, batch_size: int, beta: float, rng: np.random.Generator | None = None) -> TransitionBatch:
        """A prioritized batch; `rng` defaults to the replay's own generator."""
        if self._size == 0:
            raise ValueError("the replay holds no transitions to sample")
        rng = self._rng if rng is None else rng
        tree, c, k = self._tree, self.capacity, self.frame_stack
        slots = tree.sample_stratified(batch_size, rng)
        # w_i = (N P_i)^-beta / max_j (N P_j)^-beta = (P_min / P_i)^beta: N and the total cancel.
        priority = tree.get(slots)
        weights = np.power(priority.min() / priority, beta)

        # Frame stacks for the states and the next states in one gather: each reaches back k-1
        # frames, but never past its episode's first frame (history = frames before it, capped).
        ends = np.concatenate([slots, slots + self._next_offset[slots]])
        np.remainder(ends, c, out=ends)
        if k == 1:
            stack_slots = ends[:, None]
        else:
            stack_slots = ends[:, None] - np.minimum(self._stack_back, self._history[ends][:, None])
            np.remainder(stack_slots, c, out=stack_slots)
        frames = self._frames[stack_slots]  # (2B, k, V, V, 4)
        return TransitionBatch(
            indices=slots,
            generations=self._generation[slots],
            obs=frames[:batch_size],
            mission=self._ep_mission[self._episode[slots]].astype(np.int64),
            action=self._action[slots].astype(np.int64),
            reward=self._return[slots],
            discount=self._discount[slots],
            next_obs=frames[batch_size:],
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

    def composition(self) -> dict[str, int]:
        """Sampleable transitions held, by the origin of their episode."""
        return {name: int(count) for name, count in zip(ORIGINS, self._counts)}

    def beta_at(self, frames: int) -> float:
        """Importance-sampling exponent annealed linearly from beta_start to beta_end over beta_frames."""
        c = self.cfg
        return linear_schedule(frames, c.beta_start, c.beta_end, c.beta_frames)

    # ------------------------------------------------------------------------------- checkpoint

    _ARRAYS = (*_SLOT_ARRAYS, *_RECORD_ARRAYS, "_counts")
    _INTS = ("_cursor", "_writes", "_first_live", "_next_serial", "_size")

    def state_dict(self) -> dict:
        """A flat dict of numpy arrays and Python numbers (np.savez-able without pickle).

        Arrays are copies, so the replay may keep filling while a checkpoint is written; that costs
        about the replay's own size in memory for the duration.
        """
        state: dict = {"capacity": self.capacity, "n_step": self.n_step, "gamma": self.gamma,
                       "view_size": self.view_size, "mission_len": self.mission_len}
        for name in self._ARRAYS:
            state[name.lstrip("_")] = getattr(self, name).copy()
        for name in self._INTS:
            state[name.lstrip("_")] = int(getattr(self, name))
        tree = self._tree.state_dict()
        state["tree"] = tree["tree"]
        state["tree_max_priority"] = tree["max_priority"]
        state["rng_state"] = rng_state_to_array(self._rng)
        return state

    def load_state_dict(self, state: dict) -> None:
        for key in ("capacity", "n_step", "view_size", "mission_len"):
            if int(state[key]) != getattr(self, key):
                raise ValueError(f"replay state has {key}={state[key]}, this replay has {getattr(self, key)}")
        if float(state["gamma"]) != self.gamma:  # stored returns were computed with it
            raise ValueError(f"replay state has gamma={state['gamma']}, this replay has {self.gamma}")
        values = {name: (getattr(self, name), np.asarray(state[name.lstrip("_")])) for name in self._ARRAYS}
        for name, (target, value) in values.items():
            if value.shape != target.shape:
                raise ValueError(f"replay state {name.lstrip('_')} has shape {value.shape}, expected {target.shape}")
        self.spec.check_cells(values["_frames"][1], "replay state frames")  # all checked before any is written
        for target, value in values.values():
            target[...] = value
        for name in self._INTS:
            setattr(self, name, int(state[name.lstrip("_")]))
        self._tree.load_state_dict({"capacity": self.capacity, "tree": state["tree"],
                                    "max_priority": state["tree_max_priority"]})
        rng_state_from_array(self._rng, state["rng_state"])


class _InsertUndo:
    """What one batch insert changes, saved just before each change (the slots and records it reaches, not
    a copy of the replay), so that a failure part-way can put the replay back as it was."""

    def __init__(self, replay: PrioritizedReplay):
        self.replay, self.saved = replay, []
        self.ints = {name: getattr(replay, name) for name in replay._INTS}
        self.counts, self.max_priority = replay._counts.copy(), replay._tree.max_priority

    def save(self, start: int, span: int, record: int) -> None:
        """Before an episode is written from slot `start` over `span` slots into `record`."""
        r = self.replay
        pieces = [(slot, slot + hi - lo, _SLOT_ARRAYS) for slot, lo, hi in r._runs(start, span)]
        for lo, hi, names in pieces + [(record, record + 1, _RECORD_ARRAYS)]:
            leaves = r._tree.get(np.arange(lo, hi)) if names is _SLOT_ARRAYS else None
            self.saved.append((lo, leaves, {name: getattr(r, name)[lo:hi].copy() for name in names}))

    def roll_back(self) -> None:
        r = self.replay
        for lo, leaves, old in reversed(self.saved):  # newest first: a slot written twice ends as it began
            for name, value in old.items():
                getattr(r, name)[lo:lo + len(value)] = value
            if leaves is not None:
                r._tree.restore_run(lo, leaves)
        r._tree.max_priority = self.max_priority
        r._counts[...] = self.counts
        for name, value in self.ints.items():
            setattr(r, name, value)
