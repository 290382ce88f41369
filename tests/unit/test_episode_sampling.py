"""Whole episodes from the prioritized replay (the recurrent core's batches), checked against what was
inserted: frames from the first, padding, n-step targets, next steps, a wrapped ring, priorities."""
import numpy as np
import pytest

from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK

from tests.unit.test_replay import GAMMA, ids, make_episode, make_replay, reference_targets


def episode_of(batch, row):
    """The (episode id, step) of each frame of a batch row."""
    return ids(batch.frames[row])


def test_each_row_is_a_whole_episode_from_its_first_frame_padded_with_its_last():
    replay = make_replay(capacity=64, frame_stack=1)
    lengths = {1: 5, 2: 2, 3: 7}
    for ep_id, steps in lengths.items():
        replay.add_episode(make_episode(ep_id, steps, outcome=SUCCESS if ep_id != 2 else TIMEOUT))
    batch = replay.sample_episodes(40, beta=0.4, rng=np.random.default_rng(0))
    t_max = batch.action.shape[1]
    assert batch.frames.shape[1] == t_max + 1 and t_max == max(lengths[ep] for ep, _ in
                                                               (episode_of(batch, r)[0] for r in range(40)))
    seen = set()
    for row in range(40):
        ep_id = episode_of(batch, row)[0][0]
        steps = lengths[ep_id]
        seen.add(ep_id)
        expected = [(ep_id, min(t, steps)) for t in range(t_max + 1)]
        assert episode_of(batch, row) == expected
        assert batch.mask[row].tolist() == [1.0] * steps + [0.0] * (t_max - steps)
        assert batch.mission[row, 0] == ep_id + 3
        np.testing.assert_array_equal(batch.action[row, :steps], np.arange(steps) % 4)
        rewards = np.zeros(steps, np.float32)
        if ep_id != 2:
            rewards[-1] = 1.0
        for t, (ret, disc, nxt) in enumerate(reference_targets(rewards, terminated=ep_id != 2)):
            assert batch.reward[row, t] == pytest.approx(ret)
            assert batch.discount[row, t] == pytest.approx(disc)
            assert batch.next_step[row, t] == nxt
        # Padding: nothing to learn from, and a next step inside the row.
        assert (batch.reward[row, steps:] == 0).all() and (batch.discount[row, steps:] == 0).all()
        assert (batch.next_step[row] <= t_max).all()
    assert seen == set(lengths)
    assert batch.transitions == int(batch.mask.sum()) and batch.valid.dtype == bool


def test_an_episode_that_wraps_the_ring_comes_back_in_order():
    replay = make_replay(capacity=20, frame_stack=1)
    replay.add_episode(make_episode(1, 7))  # slots 0-7
    replay.add_episode(make_episode(2, 7))  # slots 8-15
    replay.add_episode(make_episode(3, 6))  # slots 16-19 then 0-2: evicts episode 1
    batch = replay.sample_episodes(30, beta=0.4, rng=np.random.default_rng(1))
    rows = [r for r in range(30) if episode_of(batch, r)[0][0] == 3]
    assert rows and {episode_of(batch, r)[0][0] for r in range(30)} == {2, 3}
    for r in rows:
        assert episode_of(batch, r)[:7] == [(3, t) for t in range(7)]
        assert sorted(batch.indices[r, :6] % 20) == sorted([16, 17, 18, 19, 0, 1])


def test_episodes_are_drawn_by_their_summed_priorities_and_weighted_back():
    replay = make_replay(capacity=64, frame_stack=1, alpha=1.0, priority_eps=0.0)
    replay.add_episode(make_episode(1, 4, outcome=WRONG_PICK))
    replay.add_episode(make_episode(2, 4, outcome=WRONG_PICK))
    batch = replay.sample_episodes(2, beta=1.0, rng=np.random.default_rng(0))
    assert np.allclose(batch.weights, 1.0)  # equal priorities: nothing to undo
    # Episode 1's transitions get 3x episode 2's priority: drawn 3x as often, weighted 1/3.
    slots = np.arange(4)  # episode 1 holds slots 0-3
    replay.update_priorities(slots, np.full(4, 3.0))
    replay.update_priorities(slots + 5, np.full(4, 1.0))
    counts = {1: 0, 2: 0}
    rng = np.random.default_rng(2)
    for _ in range(300):
        batch = replay.sample_episodes(4, beta=1.0, rng=rng)
        for row in range(4):
            counts[episode_of(batch, row)[0][0]] += 1
        ep_ids = [episode_of(batch, r)[0][0] for r in range(4)]
        if set(ep_ids) == {1, 2}:
            w = {e: batch.weights[r] for r, e in enumerate(ep_ids)}
            assert w[2] == pytest.approx(1.0) and w[1] == pytest.approx(1 / 3, rel=1e-5)
    share = counts[1] / (counts[1] + counts[2])
    assert 0.70 <= share <= 0.80, counts  # 0.75 expected


def test_priorities_written_back_through_the_valid_steps_only():
    replay = make_replay(capacity=64, frame_stack=1, alpha=1.0, priority_eps=0.0)
    replay.add_episode(make_episode(1, 3))
    replay.add_episode(make_episode(2, 6))
    batch = replay.sample_episodes(2, beta=0.4, rng=np.random.default_rng(0))
    td = np.where(batch.valid, 2.0, 99.0)
    applied = replay.update_priorities(batch.indices[batch.valid], td[batch.valid], batch.generations[batch.valid])
    assert applied == batch.transitions
    leaves = replay._tree.get(np.unique(batch.indices[batch.valid]))
    assert np.allclose(leaves, 2.0)


def test_an_empty_replay_or_no_episodes_is_refused():
    replay = make_replay(frame_stack=1)
    with pytest.raises(ValueError, match="no transitions"):
        replay.sample_episodes(2, beta=0.4)
    replay.add_episode(make_episode(1, 3))
    with pytest.raises(ValueError, match="n_episodes"):
        replay.sample_episodes(0, beta=0.4)
