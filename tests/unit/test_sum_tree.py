import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from higher_dist.learning.sum_tree import SumTree


def assert_consistent(tree: SumTree) -> None:
    """Every internal node equals the sum of its two children; padding leaves stay 0."""
    t = tree.tree
    for node in range(1, tree.n_leaves):
        assert t[node] == t[2 * node] + t[2 * node + 1]
    assert np.all(t[tree.n_leaves + tree.capacity:] == 0)


def test_layout_rounds_leaves_up_to_a_power_of_two():
    assert SumTree(1).n_leaves == 1
    assert SumTree(8).n_leaves == 8
    assert SumTree(9).n_leaves == 16
    with pytest.raises(ValueError):
        SumTree(0)


def test_total_matches_leaf_sum_after_many_random_updates():
    rng = np.random.default_rng(0)
    tree = SumTree(37)
    reference = np.zeros(37)
    for _ in range(50):
        idx = rng.integers(0, 37, size=rng.integers(1, 20))
        idx = np.unique(idx)
        pri = rng.random(idx.size) * 10
        tree.update(idx, pri)
        reference[idx] = pri
        assert tree.total() == pytest.approx(reference.sum(), rel=1e-12)
    np.testing.assert_array_equal(tree.get(np.arange(37)), reference)
    np.testing.assert_array_equal(tree.leaves(), reference)
    assert_consistent(tree)


def test_duplicate_indices_last_write_wins():
    tree = SumTree(8)
    tree.update(np.array([3, 5, 3, 1, 3]), np.array([1.0, 2.0, 7.0, 0.5, 4.0]))
    np.testing.assert_array_equal(tree.get(np.array([1, 3, 5])), [0.5, 4.0, 2.0])
    assert tree.total() == 6.5
    assert_consistent(tree)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 12), st.floats(0, 100)), min_size=1, max_size=30))
def test_batched_update_equals_sequential_writes(writes):
    idx = np.array([i for i, _ in writes])
    pri = np.array([p for _, p in writes])
    reference = np.zeros(13)
    for i, p in writes:
        reference[i] = p
    tree = SumTree(13)
    tree.update(idx, pri)
    np.testing.assert_array_equal(tree.leaves(), reference)
    assert tree.total() == pytest.approx(reference.sum(), rel=1e-12, abs=1e-300)
    assert_consistent(tree)


def test_update_run_matches_general_update_and_checks_bounds():
    a, b = SumTree(20), SumTree(20)
    values = np.linspace(0.1, 2.0, 7)
    a.update_run(11, values)
    b.update(np.array([17, 11, 12, 13, 14, 15, 16])[[1, 2, 3, 4, 5, 6, 0]], values)
    np.testing.assert_array_equal(a.tree, b.tree)
    with pytest.raises(IndexError):
        a.update_run(15, values)
    with pytest.raises(IndexError):
        a.update(np.array([20]), np.array([1.0]))
    with pytest.raises(ValueError):
        a.update(np.array([2]), np.array([-1.0]))
    with pytest.raises(ValueError):
        a.update(np.array([2]), np.array([np.nan]))


def test_max_priority_is_the_largest_value_ever_written():
    tree = SumTree(4)
    tree.update(np.array([0, 1]), np.array([2.0, 5.0]))
    tree.update(np.array([1]), np.array([0.0]))
    assert tree.max_priority == 5.0


def test_sampling_frequencies_follow_priorities():
    # Chi-square goodness of fit; 0.999 quantile for 6 degrees of freedom is 22.5, the bound is generous.
    priorities = np.array([0.0, 1.0, 2.0, 3.0, 0.0, 4.0, 0.5, 6.0, 2.5, 0.0])
    tree = SumTree(priorities.size)
    tree.update(np.arange(priorities.size), priorities)
    rng = np.random.default_rng(1)
    n = 100_000
    leaves = tree.sample(rng.random(n) * tree.total())
    counts = np.bincount(leaves, minlength=priorities.size)
    assert counts[priorities == 0].sum() == 0
    expected = n * priorities / priorities.sum()
    positive = priorities > 0
    chi2 = np.sum((counts[positive] - expected[positive]) ** 2 / expected[positive])
    assert chi2 < 35.0


def test_zero_priority_leaves_never_sampled_even_at_the_edges():
    tree = SumTree(10)
    # Wildly different scales make node sums round; zeros sit between and after positive leaves.
    tree.update(np.arange(10), np.array([0, 1e16, 0, 1.0, 0, 0, 3e-5, 0, 0, 0], dtype=np.float64))
    total = tree.total()
    leaf_sums = np.cumsum(tree.leaves())
    values = np.concatenate([
        [0.0, total, np.nextafter(total, np.inf), total * (1 + 1e-9), np.nextafter(total, 0)],
        leaf_sums, np.nextafter(leaf_sums, 0), np.nextafter(leaf_sums, np.inf),
        np.random.default_rng(2).random(1000) * total,
    ])
    leaves = tree.sample(values)
    assert np.all(tree.get(leaves) > 0)
    assert np.all((leaves >= 0) & (leaves < tree.capacity))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.sampled_from([0.0, 0.0, 1e-12, 0.3, 1.0, 7.0, 1e9]), min_size=1, max_size=20),
       st.floats(0, 1.5))
def test_any_value_lands_on_a_positive_leaf(priorities, fraction):
    pri = np.array(priorities)
    if pri.sum() == 0:
        pri[0] = 1.0
    tree = SumTree(pri.size)
    tree.update(np.arange(pri.size), pri)
    leaf = tree.sample(np.array([fraction * tree.total()]))
    assert tree.get(leaf)[0] > 0


def test_sampling_an_empty_tree_raises():
    with pytest.raises(ValueError):
        SumTree(4).sample(np.array([0.0]))


def test_single_leaf_tree():
    tree = SumTree(1)
    tree.update(np.array([0]), np.array([2.0]))
    assert tree.total() == 2.0
    np.testing.assert_array_equal(tree.sample(np.array([0.0, 1.9, 2.0])), [0, 0, 0])


def test_state_dict_round_trip():
    tree = SumTree(11)
    tree.update(np.arange(11), np.random.default_rng(3).random(11))
    other = SumTree(11)
    other.load_state_dict(tree.state_dict())
    np.testing.assert_array_equal(other.tree, tree.tree)
    assert other.max_priority == tree.max_priority
    values = np.linspace(0, tree.total(), 50, endpoint=False)
    np.testing.assert_array_equal(other.sample(values), tree.sample(values))
    with pytest.raises(ValueError):
        SumTree(12).load_state_dict(tree.state_dict())


def test_large_tree_uses_every_descent_and_update_path():
    # 50_000 leaves: depth 16, so sampling searches the top 12 levels and descends 4, and scattered
    # updates recompute the low levels by gathers and the high ones by slices.
    rng = np.random.default_rng(6)
    n = 50_000
    tree = SumTree(n)
    reference = rng.random(n)
    reference[rng.random(n) < 0.5] = 0.0
    tree.update(np.arange(n), reference)
    for _ in range(20):
        idx = rng.integers(0, n, size=64)
        pri = rng.random(64) * rng.integers(0, 2, size=64)  # about half zeros
        tree.update(idx, pri)
        for i, p in zip(idx, pri):  # sequential writes: the last one of a repeated index wins
            reference[i] = p
    np.testing.assert_array_equal(tree.leaves(), reference)
    t = tree.tree
    np.testing.assert_array_equal(t[1:tree.n_leaves], t[2:2 * tree.n_leaves:2] + t[3:2 * tree.n_leaves:2])
    assert tree.total() == pytest.approx(reference.sum(), rel=1e-9)

    # Frequencies over 8 coarse blocks of leaves; 7 degrees of freedom, 0.999 quantile 24.3.
    draws = 200_000
    leaves = tree.sample(rng.random(draws) * tree.total())
    assert np.all(reference[leaves] > 0)
    blocks = np.arange(n) * 8 // n
    counts = np.bincount(blocks[leaves], minlength=8)
    expected = draws * np.bincount(blocks, weights=reference, minlength=8) / reference.sum()
    assert np.sum((counts - expected) ** 2 / expected) < 40.0
    edges = np.array([0.0, tree.total(), np.nextafter(tree.total(), np.inf)])
    assert np.all(tree.get(tree.sample(edges)) > 0)
