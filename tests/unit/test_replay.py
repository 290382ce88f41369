import io
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from higher_dist.config import ReplayConfig
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode
from higher_dist.learning.replay import PrioritizedReplay
from higher_dist.world.spec import DEFAULT_SPEC

GAMMA, N_STEP = 0.9, 3
# Frames here carry identities (episode id, step) in their cells, beyond the paper world's values: a
# world whose every channel takes any byte lets them in.
MARKER_SPEC = replace(DEFAULT_SPEC, channel_values=(256, 256, 256, 256))


def make_episode(ep_id: int, steps: int, outcome: int = SUCCESS, rewards=None, relabelled=False) -> Episode:
    """Frames carry their identity: channel 0 of cell (0,0) is ep_id, channel 1 is the step t."""
    frames = np.zeros((steps + 1, 7, 7, 4), dtype=np.uint8)
    frames[:, 0, 0, 0] = ep_id
    frames[:, 0, 0, 1] = np.arange(steps + 1)
    if rewards is None:
        rewards = np.zeros(steps, dtype=np.float32)
        if outcome == SUCCESS or relabelled:
            rewards[-1] = 1.0
    mission = np.zeros(10, dtype=np.int64)
    mission[:3] = [ep_id + 3, 5, 7]
    return Episode(frames=frames, actions=(np.arange(steps) % 4).astype(np.uint8),
                   rewards=np.asarray(rewards, dtype=np.float32), mission=mission, outcome=outcome,
                   picked=np.full(4, -1, np.int8), goal=np.zeros(4, np.int8), relabelled=relabelled)


def make_replay(capacity=64, frame_stack=4, n_step=N_STEP, gamma=GAMMA, seed=0, **cfg) -> PrioritizedReplay:
    return PrioritizedReplay(ReplayConfig(capacity=capacity, **cfg), frame_stack=frame_stack,
                             n_step=n_step, gamma=gamma, spec=MARKER_SPEC, seed=seed)


def reference_targets(rewards, terminated, n=N_STEP, gamma=GAMMA):
    """Straight from the definition, one transition at a time."""
    T = len(rewards)
    out = []
    for t in range(T):
        m = min(n, T - t)
        ret = sum(gamma ** i * rewards[t + i] for i in range(m))
        disc = 0.0 if (t + m == T and terminated) else gamma ** m
        out.append((ret, disc, t + m))
    return out


def ids(stack):
    """(episode id, step) of each frame of a (k, 7, 7, 4) stack."""
    return [(int(f[0, 0, 0]), int(f[0, 0, 1])) for f in stack]


def sample_all(replay, batch=400, seed=0):
    return replay.sample(batch, beta=0.4, rng=np.random.default_rng(seed))


@pytest.mark.parametrize("outcome", [WRONG_PICK, TIMEOUT])
@pytest.mark.parametrize("steps", [6, 2])  # 2 < n: every transition has m < n
def test_n_step_targets_match_reference(outcome, steps):
    rewards = np.array([0.5, -0.25, 1.0, 0.0, 2.0, 0.75][:steps], dtype=np.float32)
    ep = make_episode(9, steps, outcome, rewards=rewards)
    replay = make_replay(frame_stack=1)
    replay.add_episode(ep)
    batch = sample_all(replay)
    ref = reference_targets(rewards, ep.terminated)
    assert set(batch.indices.tolist()) == set(range(steps))  # the final frame's slot is never drawn
    for i, slot in enumerate(batch.indices):
        ret, disc, next_t = ref[slot]
        assert batch.reward[i] == pytest.approx(ret, rel=1e-6)
        assert batch.discount[i] == pytest.approx(disc, rel=1e-6)
        assert ids(batch.next_obs[i]) == [(9, next_t)]
        assert ids(batch.obs[i]) == [(9, slot)]
        assert batch.action[i] == ep.actions[slot]
    # Spot values: the last transition of a pick ends in a terminal, a time-out bootstraps.
    last = batch.indices == steps - 1
    expected = 0.0 if outcome == WRONG_PICK else GAMMA
    np.testing.assert_allclose(batch.discount[last], expected, rtol=1e-6)


def test_batch_dtypes_and_shapes():
    replay = make_replay()
    replay.add_episode(make_episode(1, 5))
    b = replay.sample(8, beta=0.5)
    assert len(b) == 8
    assert b.indices.dtype == np.int64 and b.generations.dtype == np.int64
    assert b.obs.shape == (8, 4, 7, 7, 4) and b.obs.dtype == np.uint8
    assert b.next_obs.shape == (8, 4, 7, 7, 4) and b.next_obs.dtype == np.uint8
    assert b.mission.shape == (8, 10) and b.mission.dtype == np.int64
    assert b.action.dtype == np.int64
    assert b.reward.dtype == b.discount.dtype == b.weights.dtype == np.float32
    np.testing.assert_array_equal(b.mission[:, :3], np.tile([4, 5, 7], (8, 1)))


def test_frame_stacks_pad_with_first_frame_and_stay_in_their_episode():
    replay = make_replay(capacity=64, frame_stack=4)
    replay.add_episode(make_episode(1, 5))
    replay.add_episode(make_episode(2, 4))  # slots 6..10, right after episode 1's final frame
    batch = sample_all(replay)
    seen = set()
    for i in range(len(batch)):
        obs, nxt = ids(batch.obs[i]), ids(batch.next_obs[i])
        ep_id, t = obs[-1]
        seen.add((ep_id, t))
        assert obs == [(ep_id, max(0, t - j)) for j in (3, 2, 1, 0)]
        next_t = nxt[-1][1]
        assert nxt == [(ep_id, max(0, next_t - j)) for j in (3, 2, 1, 0)]
    assert seen == {(1, t) for t in range(5)} | {(2, t) for t in range(4)}


def test_fifo_eviction_by_whole_episodes():
    replay = make_replay(capacity=20, frame_stack=2)
    replay.add_episode(make_episode(1, 5, SUCCESS))  # slots 0-5
    replay.add_episode(make_episode(2, 5, WRONG_PICK))  # slots 6-11
    replay.add_episode(make_episode(3, 5, TIMEOUT))  # slots 12-17
    assert len(replay) == 15
    assert replay.composition() == {"success": 5, "wrong_pick": 5, "timeout": 5, "relabelled": 0}

    # 6 slots from 18 wrap to 0-3: episode 1 loses 4 slots and its slots 4-5 become unsampleable too.
    replay.add_episode(make_episode(4, 5, WRONG_PICK, relabelled=True))
    assert len(replay) == 15
    assert replay.composition() == {"success": 0, "wrong_pick": 5, "timeout": 5, "relabelled": 5}
    episodes = {ids(s)[-1][0] for s in sample_all(replay).obs}
    assert episodes == {2, 3, 4}
    for stack in sample_all(replay, seed=1).obs:
        assert len({e for e, _ in ids(stack)}) == 1

    # The cursor is at 4; six slots 4-9 reach into episode 2 (slots 6-11), which goes entirely.
    replay.add_episode(make_episode(5, 5, SUCCESS))
    assert replay.composition() == {"success": 5, "wrong_pick": 0, "timeout": 5, "relabelled": 5}
    assert {ids(s)[-1][0] for s in sample_all(replay).obs} == {3, 4, 5}


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 9), st.integers(0, 3)), min_size=1, max_size=25))
def test_eviction_matches_a_slot_level_model(episodes):
    """Against a model that tracks the owner of every slot: an episode lives while it owns all its slots."""
    capacity = 23
    replay = make_replay(capacity=capacity, frame_stack=3)
    owner = [-1] * capacity
    spans, cursor = {}, 0
    for ep_id, (steps, kind) in enumerate(episodes):
        outcome, relabelled = (WRONG_PICK, True) if kind == 3 else (kind, False)
        replay.add_episode(make_episode(ep_id, steps, outcome, relabelled=relabelled))
        slots = [(cursor + i) % capacity for i in range(steps + 1)]
        for slot in slots:
            owner[slot] = ep_id
        spans[ep_id] = (slots, steps, "relabelled" if relabelled else ("success", "wrong_pick", "timeout")[outcome])
        cursor = (cursor + steps + 1) % capacity
        live = {e for e, (sl, _, _) in spans.items() if all(owner[x] == e for x in sl)}
        assert len(replay) == sum(spans[e][1] for e in live)
        expected = {"success": 0, "wrong_pick": 0, "timeout": 0, "relabelled": 0}
        for e in live:
            expected[spans[e][2]] += spans[e][1]
        assert replay.composition() == expected
        batch = replay.sample(2 * len(replay) + 2, beta=0.4)  # equal priorities: covers every transition
        seen = {ids(stack)[-1] for stack in batch.obs}
        assert seen == {(e, t) for e in live for t in range(spans[e][1])}
        for stack in np.concatenate([batch.obs, batch.next_obs]):
            assert len({e for e, _ in ids(stack)}) == 1


def test_episode_filling_the_whole_buffer_evicts_everything():
    replay = make_replay(capacity=12, frame_stack=1)
    replay.add_episode(make_episode(1, 3))
    replay.add_episode(make_episode(2, 11))
    assert len(replay) == 11
    assert {ids(s)[-1][0] for s in sample_all(replay).obs} == {2}
    with pytest.raises(ValueError):
        replay.add_episode(make_episode(3, 12))  # 13 slots > capacity 12


def test_invalid_episodes_are_refused():
    replay = make_replay()
    ep = make_episode(1, 4)
    with pytest.raises(ValueError):
        replay.add_episode(Episode(**{**ep.__dict__, "frames": ep.frames[:-1]}))
    with pytest.raises(ValueError):
        replay.add_episode(Episode(**{**ep.__dict__, "mission": np.full(10, 40_000)}))
    with pytest.raises(ValueError):
        make_replay().sample(4, beta=0.4)  # empty


def test_cells_outside_the_worlds_values_are_refused_at_insert_and_on_load():
    """The replay checks every frame's cells as it comes in (the learner's compiled loss then need not):
    a value a channel lacks, in any cell of any frame, refuses the batch and stores none of it; a
    checkpoint whose frames hold one is refused before anything is loaded."""
    world = PrioritizedReplay(ReplayConfig(capacity=64), frame_stack=4, n_step=N_STEP, gamma=GAMMA, seed=0)
    good = make_episode(1, 4)
    good.frames[:, 0, 0, :2] = 0  # the markers, beyond this world's values
    world.add_episode(good)
    for channel, value in enumerate(DEFAULT_SPEC.channel_max):
        bad = make_episode(2, 5)
        bad.frames[:, 0, 0, :2] = 0
        bad.frames[3, 6, 2, channel] = value + 1
        before = world.state_dict()
        with pytest.raises(ValueError, match="out of range"):
            world.add_episodes([good, bad])
        after = world.state_dict()
        assert all(np.array_equal(before[k], after[k]) for k in before)
    with pytest.raises(ValueError, match="integer"):
        world.add_episode(Episode(**{**good.__dict__, "frames": good.frames.astype(np.float32)}))
    state = world.state_dict()
    state["frames"] = state["frames"].copy()
    state["frames"][10, 3, 3, 0] = DEFAULT_SPEC.channel_max[0] + 1
    fresh = PrioritizedReplay(ReplayConfig(capacity=64), frame_stack=4, n_step=N_STEP, gamma=GAMMA, seed=0)
    with pytest.raises(ValueError, match="out of range"):
        fresh.load_state_dict(state)
    assert len(fresh) == 0 and not fresh.state_dict()["frames"].any()


def test_importance_weights_match_numpy_formula():
    alpha, beta = 0.6, 0.7
    replay = make_replay(capacity=64, alpha=alpha, priority_eps=0.01)
    replay.add_episode(make_episode(1, 10))
    replay.add_episode(make_episode(2, 10))
    slots = np.array([t for t in range(10)] + [11 + t for t in range(10)])
    td = np.linspace(0.0, 3.0, slots.size)
    assert replay.update_priorities(slots, td) == slots.size
    batch = replay.sample(32, beta=beta, rng=np.random.default_rng(4))
    prio = (td + 0.01) ** alpha
    prob = dict(zip(slots.tolist(), prio / prio.sum()))
    w = (len(replay) * np.array([prob[s] for s in batch.indices.tolist()])) ** -beta
    np.testing.assert_allclose(batch.weights, w / w.max(), rtol=1e-6)
    assert batch.weights.max() == pytest.approx(1.0)


def test_update_priorities_changes_sampling():
    replay = make_replay(capacity=64)
    replay.add_episode(make_episode(1, 20))
    replay.update_priorities(np.arange(20), np.full(20, 0.01))
    replay.update_priorities(np.array([7]), np.array([50.0]))
    counts = np.bincount(replay.sample(1000, beta=0.4).indices, minlength=21)
    # p7 / sum = (50.001^0.6) / (50.001^0.6 + 19 * 0.011^0.6) ~ 0.87
    assert counts[7] > 800
    assert counts[20] == 0  # final frame


def test_new_data_gets_the_max_priority_seen():
    replay = make_replay(capacity=64, alpha=1.0, priority_eps=0.0)
    replay.add_episode(make_episode(1, 4))
    replay.update_priorities(np.array([0, 1]), np.array([3.0, 0.5]))
    replay.add_episode(make_episode(2, 4))  # slots 5..9
    counts = np.bincount(replay.sample(2000, beta=0.4).indices, minlength=10)
    # Tree mass: 3 + 0.5 + 1 + 1 from episode 1, 4 * 3 from episode 2.
    assert counts[5:9].sum() / 2000 == pytest.approx(12 / 17.5, abs=0.04)


def test_stale_priority_updates_are_ignored():
    replay = make_replay(capacity=12, frame_stack=1)
    replay.add_episode(make_episode(1, 5))  # slots 0-5
    batch = replay.sample(16, beta=0.4)
    replay.add_episode(make_episode(2, 3))  # slots 6-9
    replay.add_episode(make_episode(3, 3))  # wraps 10,11,0,1: episode 1 evicted, slots 2-5 free
    applied = replay.update_priorities(batch.indices, np.full(16, 100.0), batch.generations)
    assert applied == 0
    # Without generations, free slots (2-5) still refuse, but rewritten ones (0, 1) would accept.
    assert replay.update_priorities(np.array([2, 3, 4]), np.full(3, 100.0)) == 0
    assert replay.update_priorities(np.array([0]), np.array([100.0])) == 1
    fresh = replay.sample(16, beta=0.4)
    assert replay.update_priorities(fresh.indices, np.ones(16), fresh.generations) == 16


def test_beta_annealing():
    replay = make_replay(beta_start=0.4, beta_end=1.0, beta_frames=1000)
    assert replay.beta_at(0) == pytest.approx(0.4)
    assert replay.beta_at(500) == pytest.approx(0.7)
    assert replay.beta_at(1000) == pytest.approx(1.0)
    assert replay.beta_at(10_000) == pytest.approx(1.0)


def fill(replay, rng):
    for i in range(12):
        replay.add_episode(make_episode(i, int(rng.integers(1, 9)), int(rng.integers(0, 3)),
                                        relabelled=bool(rng.integers(0, 2))))
    batch = replay.sample(16, beta=0.5)
    replay.update_priorities(batch.indices, rng.random(16) * 4, batch.generations)


def assert_same_batch(a, b):
    for field in ("indices", "generations", "obs", "mission", "action", "reward", "discount",
                  "next_obs", "weights"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


def test_state_dict_round_trip_through_npz():
    rng = np.random.default_rng(5)
    replay = make_replay(capacity=40, seed=3)
    fill(replay, rng)
    buffer = io.BytesIO()
    np.savez(buffer, **replay.state_dict())  # plain arrays and numbers: no pickle needed
    buffer.seek(0)
    with np.load(buffer, allow_pickle=False) as data:
        state = {key: data[key] for key in data.files}
    restored = make_replay(capacity=40, seed=99)
    restored.load_state_dict(state)
    assert len(restored) == len(replay)
    assert restored.composition() == replay.composition()
    np.testing.assert_array_equal(restored.state_dict()["tree"], replay.state_dict()["tree"])
    assert_same_batch(restored.sample(32, 0.6, rng=np.random.default_rng(7)),
                      replay.sample(32, 0.6, rng=np.random.default_rng(7)))
    assert_same_batch(restored.sample(32, 0.6), replay.sample(32, 0.6))  # own RNG restored too
    # Both keep evolving identically.
    ep = make_episode(50, 6, TIMEOUT)
    replay.add_episode(ep)
    restored.add_episode(ep)
    assert_same_batch(restored.sample(32, 0.6), replay.sample(32, 0.6))
    with pytest.raises(ValueError):
        make_replay(capacity=41).load_state_dict(state)


def test_timeouts_can_be_stored_terminal_as_the_papers_code_did():
    ep = make_episode(4, 6, TIMEOUT)
    for terminal in (False, True):
        replay = make_replay(frame_stack=1, timeouts_terminal=terminal)
        replay.add_episode(ep)
        batch = sample_all(replay)
        ref = reference_targets(ep.rewards, terminal)
        for i, slot in enumerate(batch.indices):
            assert batch.discount[i] == pytest.approx(ref[slot][1], rel=1e-6)
        last = batch.indices == 5
        np.testing.assert_allclose(batch.discount[last], 0.0 if terminal else GAMMA, rtol=1e-6)
