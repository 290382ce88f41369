"""The text `higher-render` writes under a BabyAI episode: the first achieved outcome by the level's verb,
the count of the ones after it; real episodes of a go-to and a pickup level, a door on an open level."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from higher_dist import render, render_babyai
from higher_dist.config_presets import make_config
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.world import babyai_language as lang
from higher_dist.world.spec import SUCCESS, TIMEOUT, WorldSpec


def failures(level: str, n: int) -> tuple[WorldSpec, list]:
    cfg = make_config("her", level)
    episodes = real_episodes(cfg.world, n, seed=5)
    return WorldSpec.of(cfg.world), episodes


def test_a_go_to_time_out_names_what_it_reached_first_and_counts_the_rest():
    spec, episodes = failures("BabyAI-GoToLocal-v0", 90)
    for ep in episodes:
        text = render.outcome_text(ep, spec)
        if ep.outcome == SUCCESS:
            assert text == f"SUCCESS after {ep.length} steps"
            continue
        assert ep.outcome == TIMEOUT and text.startswith(f"TIME-OUT after {ep.length} steps")
        if ep.pick_step < 0:
            assert text == f"TIME-OUT after {ep.length} steps"
            continue
        what = f"a {lang.COLORS[ep.picked[0]]} {lang.TYPES[ep.picked[1]]}"
        first = f"TIME-OUT after {ep.length} steps, reached {what} first (step {ep.pick_step + 1})"
        assert text == first + (f", then {ep.n_outcomes - 1} more" if ep.n_outcomes > 1 else "")
    assert any(ep.n_outcomes > 1 for ep in episodes)  # the count was exercised


def test_the_verb_is_the_levels_kind_and_a_door_renders():
    spec, episodes = failures("BabyAI-PickupDist-v0", 30)
    ep = next(e for e in episodes if e.outcome == TIMEOUT and e.pick_step >= 0)
    assert ", picked up a " in render.outcome_text(ep, spec)
    door = replace(ep, picked=np.array([0, lang.DOOR, 0, 0], np.int8))
    assert render_babyai.outcome_text(door, "open").startswith(
        f"TIME-OUT after {ep.length} steps, opened a red door first (step {ep.pick_step + 1})")
    assert render_babyai.object_text(door.picked) == "a red door"
    assert ", reached a red door first" in render_babyai.outcome_text(door, "goto")
