"""The object space and its fixed train / held-out split."""
from dataclasses import replace

import numpy as np
import pytest

from higher_dist.config import WorldConfig
from higher_dist.config_presets import small_world
from higher_dist.world.objects import ObjectSpace


def as_set(objects):
    return {tuple(o) for o in objects.tolist()}


def every_value_present(objects, space):
    return all(set(objects[:, a].tolist()) == set(space.values(a).tolist()) for a in range(4))


def test_paper_split_is_240_60_disjoint_covering_and_fixed_by_the_seed():
    space = ObjectSpace(WorldConfig())
    assert space.all_objects.shape == (300, 4) and len(as_set(space.all_objects)) == 300
    assert len(space.train_objects) == 240 and len(space.heldout_objects) == 60
    assert not as_set(space.train_objects) & as_set(space.heldout_objects)
    assert as_set(space.train_objects) | as_set(space.heldout_objects) == as_set(space.all_objects)
    assert every_value_present(space.train_objects, space)
    assert every_value_present(space.heldout_objects, space)
    again = ObjectSpace(WorldConfig())
    np.testing.assert_array_equal(space.heldout_objects, again.heldout_objects)
    other = ObjectSpace(replace(WorldConfig(), split_seed=1))
    assert as_set(other.heldout_objects) != as_set(space.heldout_objects)


def test_small_world_split_keeps_every_value_in_both_sets():
    space = ObjectSpace(small_world())
    assert len(space.all_objects) == 4
    assert len(space.train_objects) == 2 and len(space.heldout_objects) == 2
    assert every_value_present(space.train_objects, space)
    assert every_value_present(space.heldout_objects, space)
    for seed in range(10):
        s = ObjectSpace(replace(small_world(), split_seed=seed))
        assert every_value_present(s.train_objects, s) and every_value_present(s.heldout_objects, s)


def test_subsets_keep_global_indices():
    space = ObjectSpace(small_world())  # colors red, green; shade neutral; size medium
    assert space.values(0).tolist() == [0, 1]
    assert space.values(2).tolist() == [2] and space.values(3).tolist() == [2]
    assert set(space.all_objects[:, 2].tolist()) == {2}


@pytest.mark.parametrize("heldout", [1, 3])
def test_impossible_splits_raise_a_clear_error(heldout):
    cfg = replace(small_world(), heldout_count=heldout)  # 4 objects: 1 or 3 held out cannot cover both
    with pytest.raises(ValueError, match="heldout_count"):
        ObjectSpace(cfg)


def test_no_heldout_set_when_heldout_count_is_zero():
    space = ObjectSpace(replace(small_world(), heldout_count=0))
    assert len(space.train_objects) == 4 and len(space.heldout_objects) == 0
    with pytest.raises(ValueError, match="held-out"):
        space.objects("heldout")


def test_objects_are_read_only():
    space = ObjectSpace(WorldConfig())
    with pytest.raises(ValueError):
        space.train_objects[0, 0] = 5
