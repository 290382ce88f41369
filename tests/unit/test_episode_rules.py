"""The meaning of an episode lives beside its world (world/episode_rules.py): the world's own episodes pass
its check, the reward rule the world pays by is the one the check expects, and the wire names no family."""
from __future__ import annotations

import pathlib
import re
from dataclasses import replace

import numpy as np
import pytest

from higher_dist.config import WorldConfig
from higher_dist.config_presets import make_config
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import pack_episodes
from higher_dist.world.episode_rules import episode_faults
from higher_dist.world.grid import pick_reward
from higher_dist.world.spec import TIMEOUT, WRONG_PICK, WorldSpec

WIRE = pathlib.Path(__file__).resolve().parents[2] / "higher_dist" / "wire"


def _faults(spec: WorldSpec, episodes) -> list[str]:
    reasons = [""] * len(episodes)
    episode_faults(spec, pack_episodes(episodes)[1], reasons)
    return reasons


def test_pick_reward_is_one_for_the_goal_and_a_quarter_per_attribute_when_shaped():
    goal = np.array([[2, 1, 3, 0]] * 3)
    picked = np.array([[2, 1, 3, 0], [2, 1, 0, 1], [0, 0, 0, 1]])
    np.testing.assert_array_equal(pick_reward(picked, goal, shaping=False), [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(pick_reward(picked, goal, shaping=True), [1.0, 0.5, 0.0])


@pytest.mark.parametrize("shaping", [False, True])
def test_the_worlds_own_episodes_mean_what_its_check_expects(shaping):
    """The world pays by `pick_reward` when stepping; the check expects the same, shaped or not."""
    world = replace(WorldConfig(), reward_shaping=shaping)
    spec = WorldSpec.of(world)
    episodes = real_episodes(world, 60, seed=4, relabelled=True)
    assert _faults(spec, episodes) == [""] * len(episodes)
    wrong = [ep for ep in episodes if ep.outcome == WRONG_PICK and not ep.relabelled]
    paid = [float(ep.rewards[-1]) for ep in wrong]
    assert (max(paid) > 0) == shaping  # a shaped wrong pick that shares an attribute is paid for it
    # The other rule's reward on the same episodes is a lie about this world.
    lied = [replace(ep, rewards=ep.rewards.copy()) for ep in wrong]
    for ep in lied:
        ep.rewards[-1] = pick_reward(ep.picked[None], ep.goal[None], not shaping)[0]
    changed = [i for i, ep in enumerate(lied) if ep.rewards[-1] != wrong[i].rewards[-1]]
    assert changed and [_faults(spec, [lied[i]])[0] for i in changed] == ["reward"] * len(changed)


def test_a_babyai_levels_episodes_pass_its_rules_even_where_a_pick_goes_on():
    cfg = make_config("her", "BabyAI-PickupDist-v0")
    spec = WorldSpec.of(cfg.world)
    episodes = real_episodes(cfg.world, 30, seed=2, relabelled=True)
    assert _faults(spec, episodes) == [""] * len(episodes)
    # A pickup that did not end the episode: the level's rule, a lie on the paper world (a pick ends it).
    went_on = [ep for ep in episodes if ep.outcome == TIMEOUT and 0 <= ep.pick_step < ep.length - 1]
    assert went_on


def test_the_wire_names_no_world_family():
    """What an episode means per family is the world's; the wire checks shapes, types and ranges only."""
    for path in sorted(WIRE.glob("*.py")):
        source = path.read_text()
        found = re.findall(r"babyai|fetchattr|\.family\b", source, flags=re.IGNORECASE)
        assert not found, f"{path.name} names a world family: {sorted(set(found))}"
