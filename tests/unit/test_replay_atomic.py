"""A replay insert is all or nothing: a batch of episodes whose insert fails part-way (an internal step made
to raise) leaves the replay exactly as it was (size, sum tree, slots, records, counters, RNG), and the
replay then goes on as if the failed batch had never been offered."""
from __future__ import annotations

import numpy as np
import pytest

from higher_dist.config import ReplayConfig
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode
from higher_dist.learning.replay import PrioritizedReplay
from tests.unit.test_replay import MARKER_SPEC

CAPACITY = 64


def episode(ep_id: int, steps: int, outcome: int = SUCCESS) -> Episode:
    frames = np.zeros((steps + 1, 7, 7, 4), dtype=np.uint8)
    frames[:, 0, 0, 0] = ep_id % 256
    frames[:, 0, 0, 1] = np.arange(steps + 1)
    rewards = np.zeros(steps, dtype=np.float32)
    rewards[-1] = 1.0 if outcome == SUCCESS else 0.0
    mission = np.zeros(10, dtype=np.int64)
    mission[:2] = [ep_id % 50 + 3, 5]
    return Episode(frames=frames, actions=(np.arange(steps) % 4).astype(np.uint8), rewards=rewards,
                   mission=mission, outcome=outcome, picked=np.full(4, -1, np.int8), goal=np.zeros(4, np.int8))


def filled_replay() -> PrioritizedReplay:
    """A replay that has wrapped around its ring, with priorities that are not all the maximum."""
    replay = PrioritizedReplay(ReplayConfig(capacity=CAPACITY), frame_stack=4, n_step=3, gamma=0.9, spec=MARKER_SPEC,
                               seed=7)
    outcomes = (SUCCESS, WRONG_PICK, TIMEOUT)
    replay.add_episodes([episode(i, 3 + i % 5, outcomes[i % 3]) for i in range(20)])
    batch = replay.sample(16, beta=0.4)
    replay.update_priorities(batch.indices, np.linspace(0.1, 3.0, 16), batch.generations)
    return replay


def state(replay: PrioritizedReplay) -> dict:
    return {**replay.state_dict(), "len": len(replay), "total": replay._tree.total(),
            "max_priority": replay._tree.max_priority}


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key


def fail_on_call(monkeypatch, obj, name: str, call: int) -> list[int]:
    """Make obj.name raise on its `call`-th call (1-based); earlier calls do the real work."""
    real, calls = getattr(obj, name), []

    def wrapped(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            raise RuntimeError(f"injected failure in {name}")
        return real(*args, **kwargs)

    monkeypatch.setattr(obj, name, wrapped)
    return calls


# (what fails, on which call): the tree write of the third episode (its slots already written), the
# write of the fourth episode, the eviction for the second one; and a batch larger than the ring, whose
# later episodes overwrite its earlier ones before the failure.
CASES = [("tree", "update_run", 3, 6), ("replay", "_write", 4, 6), ("replay", "_evict_for", 2, 6),
         ("tree", "update_run", 14, 16)]


@pytest.mark.parametrize("target,name,call,n_episodes", CASES)
def test_a_failure_part_way_through_a_batch_leaves_the_replay_exactly_as_it_was(monkeypatch, target, name, call,
                                                                              n_episodes):
    replay, twin = filled_replay(), filled_replay()
    before = state(replay)
    batch = [episode(100 + i, 6) for i in range(n_episodes)]
    assert sum(ep.length + 1 for ep in batch) > (CAPACITY if n_episodes > 10 else 0)
    calls = fail_on_call(monkeypatch, replay._tree if target == "tree" else replay, name, call)
    with pytest.raises(RuntimeError, match=f"injected failure in {name}"):
        replay.add_episodes(batch)
    assert len(calls) == call  # it failed where intended, after earlier steps had written
    monkeypatch.undo()
    after = state(replay)
    assert after["len"] == before["len"] and after["total"] == before["total"]
    assert_same(after, before)
    # And it goes on as a replay that was never offered the batch: same inserts, same samples.
    more = [episode(200 + i, 4) for i in range(3)]
    replay.add_episodes(more)
    twin.add_episodes(more)
    assert_same(state(replay), state(twin))
    a, b = replay.sample(8, beta=0.4), twin.sample(8, beta=0.4)
    assert np.array_equal(a.indices, b.indices) and np.array_equal(a.obs, b.obs)


def test_an_invalid_episode_anywhere_in_a_batch_stores_none_of_it():
    replay = filled_replay()
    before = state(replay)
    bad = episode(300, 5)
    bad.rewards = np.zeros(4, dtype=np.float32)  # one reward short of its actions
    with pytest.raises(ValueError, match="rewards have shape"):
        replay.add_episodes([episode(301, 5), episode(302, 5), bad])
    assert_same(state(replay), before)


def test_a_batch_that_succeeds_stores_every_transition():
    replay = filled_replay()
    replay.add_episodes([episode(40 + i, 5) for i in range(2)])
    # New transitions get the largest priority: a stratified batch of 400 reaches every one of them.
    held = replay.sample(400, beta=0.4, rng=np.random.default_rng(0))
    ids = {(int(f[-1, 0, 0, 0]), int(f[-1, 0, 0, 1])) for f in held.obs}
    assert {(40 + i, t) for i in range(2) for t in range(5)} <= ids
