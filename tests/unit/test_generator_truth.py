"""What the generator's accuracy is judged against on a BabyAI level (`WorldSpec.fulfilled_by`): the object in
front in the pair's view, with the location the mission names. A location the mission names is one the world's
own outcome record agrees with, and a description naming another location is judged wrong."""
from __future__ import annotations

import numpy as np

from higher_dist.config_presets import make_config
from higher_dist.learning.episode import SUCCESS
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.world.spec import WorldSpec

LEVEL = "BabyAI-OpenDoorLoc-v0"  # every mission names a location: "open the door on your left"


def test_the_truth_of_a_success_holds_the_location_its_mission_names():
    cfg = make_config("higher", LEVEL)
    spec = WorldSpec.of(cfg.world)
    wins = [ep for ep in real_episodes(cfg.world, 60, seed=5) if ep.outcome == SUCCESS]
    assert len(wins) >= 10
    views = np.stack([ep.frames[ep.length - 1 + spec.outcome_view_offset] for ep in wins])
    missions = np.stack([ep.mission for ep in wins])
    truth = spec.fulfilled_by(views, missions)
    named, ok = spec.language.parse_many(missions)
    assert ok.all() and (named[:, 2] >= 0).all()
    assert (truth[:, 1] == 3).all() and (truth[:, 2] == 1 << named[:, 2]).all()  # a door; the named location
    assert spec.language.satisfies(named, truth).all()  # the mission itself is right
    other = named.copy()
    other[:, 2] = (named[:, 2] + 1) % 4
    assert not spec.language.satisfies(other, truth).any()  # another location is judged wrong
    unnamed = named.copy()
    unnamed[:, 2] = -1
    assert spec.language.satisfies(unnamed, truth).all()  # "open the door": any door is right
    # The world's record of the winning toggle agrees: its location mask holds the mission's location.
    checked = 0
    for ep, loc in zip(wins, named[:, 2]):
        steps = ep.outcome_steps()
        if steps and steps[-1] == ep.length - 1:
            assert ep.outcome_attrs(len(steps) - 1)[2] >> loc & 1
            checked += 1
    assert checked >= len(wins) // 2


def test_on_fetchattr_the_truth_is_the_mission():
    spec = WorldSpec.of(make_config("higher", "small").world)
    eps = [ep for ep in real_episodes(make_config("higher", "small").world, 80, seed=2) if ep.outcome == SUCCESS]
    assert eps
    truth = spec.fulfilled_by(np.stack([ep.frames[ep.length - 1] for ep in eps]), np.stack([ep.mission for ep in eps]))
    assert (truth == np.stack([ep.goal for ep in eps])).all()
