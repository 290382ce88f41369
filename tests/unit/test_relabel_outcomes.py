"""Several relabelled copies per failed BabyAI episode, one per distinct achieved outcome, on real episodes of
a go-to level (and a pickup level where the frame the generator describes differs): how many copies, where
each ends, what it says, the seeded choice beyond `relabel.max_per_episode`, what the learned relabeller may
read, which frame the generator's dataset keeps, the config's bounds and the learner's update budget."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from higher_dist.config import ConfigError
from higher_dist.config_presets import make_config
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode
from higher_dist.learning.hindsight.generator_data import GeneratorDataset
from higher_dist.learning.hindsight.relabel import ExpertRelabel, LearnedRelabel, make_relabel_strategy
from higher_dist.learning.learner import Learner
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.world.spec import WorldSpec
from support.tripwire import PassedAlong

torch.set_num_threads(1)  # a test shares the machine

GOTO, PICKUP, OPEN = "BabyAI-GoToLocal-v0", "BabyAI-PickupDist-v0", "BabyAI-OpenRedDoor-v0"
PICKUP_LOC = "BabyAI-PickupLoc-v0"  # its missions may name a location: the generator is told where


def level(name: str, n: int, seed: int):
    cfg = make_config("her", name)
    return cfg, WorldSpec.of(cfg.world), real_episodes(cfg.world, n, seed)


GOTO_CFG, GOTO_SPEC, GOTO_EPISODES = level(GOTO, 240, seed=7)
FAILED = [ep for ep in GOTO_EPISODES if ep.outcome != SUCCESS and ep.pick_step >= 0]


def owner(copy: Episode, originals: list[Episode]) -> int:
    """The index of the original a copy was cut from (a copy's frames are a slice of its original's)."""
    return next(i for i, ep in enumerate(originals) if np.shares_memory(copy.frames, ep.frames))


def test_the_go_to_level_gives_failures_with_more_outcomes_than_the_smaller_limits():
    kinds = {(ep.outcome, ep.pick_step >= 0) for ep in GOTO_EPISODES}
    assert {(SUCCESS, True), (TIMEOUT, True), (TIMEOUT, False)} <= kinds
    assert GOTO_SPEC.level_kind == "goto" and GOTO_SPEC.outcome_view_offset == 1
    assert max(ep.n_outcomes for ep in FAILED) > 2  # so that m = 1 and 2 must choose


@pytest.mark.parametrize("most", [1, 2, 4, 8])
def test_the_expert_makes_one_copy_per_chosen_distinct_outcome(most):
    strategy = ExpertRelabel(seed=0, spec=GOTO_SPEC, max_per_episode=most)
    copies = strategy.relabel(GOTO_EPISODES)
    assert len(copies) == sum(min(ep.n_outcomes, most) for ep in FAILED) > 20
    assert strategy.metrics()["relabel_contradicting"] == 0 and strategy.metrics()["relabel_accuracy"] == 1.0
    ends: dict[int, list[int]] = {}
    for copy in copies:
        ep = FAILED[owner(copy, FAILED)]
        steps = ep.outcome_steps()
        assert copy.relabelled and copy.outcome == WRONG_PICK and copy.pick_step in steps
        k = steps.index(copy.pick_step)
        ends.setdefault(id(ep), []).append(k)
        assert copy.length == copy.pick_step + 1 and (copy.frames == ep.frames[: copy.length + 1]).all()
        assert (copy.actions == ep.actions[: copy.length]).all() and not copy.rewards[:-1].any()
        assert copy.rewards[-1] == pytest.approx(float(GOTO_SPEC.pick_reward(copy.pick_step + 1)))
        described = GOTO_SPEC.language.parse(copy.mission)
        truth = ep.outcome_attrs(k)
        assert described is not None and (described[:2] == truth[:2]).all() and described[2] == -1
        assert (copy.picked == truth).all()
        # The copy ends at its outcome: it records that one, never the ones after it.
        assert copy.n_outcomes == 1 and (copy.later_step == -1).all() and (copy.later_achieved == -1).all()
    for ep in FAILED:
        chosen = ends.get(id(ep), [])
        assert len(chosen) == min(ep.n_outcomes, most) and len(set(chosen)) == len(chosen)
        assert not ep.relabelled and ep.outcome == TIMEOUT  # the original is untouched


def test_on_a_level_that_names_locations_the_expert_names_one_the_object_is_in():
    cfg, spec, episodes = level(PICKUP_LOC, 160, seed=4)
    failed = [ep for ep in episodes if ep.outcome != SUCCESS and ep.pick_step >= 0]
    strategy = ExpertRelabel(seed=0, spec=spec, max_per_episode=8)
    copies = strategy.relabel(episodes)
    assert len(copies) == sum(ep.n_outcomes for ep in failed) > 10
    assert strategy.metrics()["relabel_accuracy"] == 1.0
    named = []
    for copy in copies:
        ep = failed[owner(copy, failed)]
        truth = ep.outcome_attrs(ep.outcome_steps().index(copy.pick_step))
        described = spec.language.parse(copy.mission)
        assert (described[:2] == truth[:2]).all() and described[3] == truth[3]  # colour, type, the article
        if truth[2] > 0:  # a location describes the object: one it is in is named
            assert described[2] >= 0 and truth[2] >> described[2] & 1
            named.append(int(described[2]))
        else:
            assert described[2] == -1
    assert len(named) > 10 and len(set(named)) >= 3
    # Which of the object's locations is named comes from the relabeler's seeded stream.
    again = ExpertRelabel(seed=0, spec=spec, max_per_episode=8).relabel(episodes)
    assert [c.mission.tolist() for c in again] == [c.mission.tolist() for c in copies]


def test_the_choice_beyond_the_limit_is_reproducible_for_a_seed_and_differs_across_seeds():
    def chosen(seed: int) -> list[tuple[int, int]]:
        copies = ExpertRelabel(seed=seed, spec=GOTO_SPEC, max_per_episode=1).relabel(GOTO_EPISODES)
        return [(owner(c, FAILED), c.pick_step) for c in copies]

    assert chosen(3) == chosen(3)
    assert chosen(3) != chosen(4)
    # Below the limit nothing is left to chance: every outcome, whatever the seed.
    full = [ExpertRelabel(seed=s, spec=GOTO_SPEC, max_per_episode=8).relabel(GOTO_EPISODES) for s in (3, 4)]
    assert [c.pick_step for c in full[0]] == [c.pick_step for c in full[1]]


def test_relabelled_copies_are_never_relabelled_again():
    strategy = ExpertRelabel(seed=0, spec=GOTO_SPEC, max_per_episode=8)
    copies = strategy.relabel(GOTO_EPISODES)
    considered = strategy.metrics()["relabel_considered"]
    assert strategy.relabel(copies) == [] and strategy.metrics()["relabel_considered"] == considered
    again = ExpertRelabel(seed=0, spec=GOTO_SPEC, max_per_episode=8).relabel(GOTO_EPISODES + copies)
    assert len(again) == len(copies)




def front_describer(spec: WorldSpec, seen: list[np.ndarray]):
    """A generator that reads only its inputs: it names the object in front of the agent and, where it is
    told where that object lay seen from the start, the first location that says so, as an exact generator
    would; it records what it was shown."""

    def generate(views, where=None, seed=None):
        seen.append(np.array(views))
        attrs = spec.front_object(views)
        attrs[:, 2], attrs[:, 3] = -1, 0
        if where is not None:
            where = np.asarray(where)
            first_bit = np.array([(w & -w).bit_length() - 1 if w else -1 for w in where.tolist()])
            attrs[:, 2] = first_bit
        return spec.language.mission_tokens(attrs)

    return generate


@pytest.mark.parametrize("name", [GOTO, PICKUP, PICKUP_LOC])
def test_the_learned_relabeller_describes_the_view_that_shows_each_outcome_and_reads_nothing_else(name, monkeypatch):
    cfg, spec, episodes = (GOTO_CFG, GOTO_SPEC, GOTO_EPISODES) if name == GOTO else level(name, 160, seed=2)
    failed = [ep for ep in episodes if ep.outcome != SUCCESS and ep.pick_step >= 0]
    # The gate opens on the first pair: no training is needed to ask the generator.
    strategy = LearnedRelabel(replace(cfg.generator, n_min=1, min_accuracy=0.0), spec, seed=0, max_per_episode=8)
    strategy.observe(episodes)
    assert strategy.trainer.gate_open
    seen: list[np.ndarray] = []
    monkeypatch.setattr(strategy.trainer, "generate", front_describer(spec, seen))
    copies = strategy.relabel(episodes)

    offset = 1 if name == GOTO else 0
    assert spec.outcome_view_offset == offset
    expected = [ep.frames[s + offset] for ep in failed for s in ep.outcome_steps()]
    assert len(seen) == 1 and len(seen[0]) == len(expected) > 10
    np.testing.assert_array_equal(seen[0], np.stack(expected))
    assert any(not (ep.frames[s] == ep.frames[s + 1]).all() for ep in failed for s in ep.outcome_steps())
    # Those views show what was achieved: an exact describer of them names each outcome's object (and on a
    # level that names locations, one of the locations minigrid's rule gives it, from the reckoned mask).
    assert strategy.metrics()["relabel_accuracy"] == 1.0
    if spec.has_locations:
        named = [spec.language.parse(c.mission)[2] for c in copies]
        assert sum(loc >= 0 for loc in named) > 10
    assert len(copies) + strategy.metrics()["relabel_contradicting"] == len(expected)

    # Blind to ground truth: the same missions when what was achieved and the goal cannot be read.
    scored = []
    monkeypatch.setattr(strategy, "_score", lambda outcomes, attrs: scored.append(len(outcomes)))
    blind = [replace(ep, picked=PassedAlong(), later_achieved=PassedAlong(), goal=PassedAlong()) for ep in failed]
    again = strategy.relabel(blind)
    assert [c.mission.tolist() for c in again] == [c.mission.tolist() for c in copies]
    assert [c.pick_step for c in again] == [c.pick_step for c in copies] and scored == [len(copies)]


def opened_door(spec: WorldSpec, length: int) -> Episode:
    """A successful episode of an open level whose every frame differs (the step number in each cell)."""
    frames = np.zeros((length + 1, *spec.view_shape), np.uint8)
    frames[:, :, :, 0] = np.arange(length + 1)[:, None, None]
    rewards = np.zeros(length, np.float32)
    rewards[-1] = float(spec.pick_reward(length))
    mission = spec.language.mission_tokens(np.array([[0, 3, -1, 0]]))[0]  # "open the red door"
    return Episode(frames=frames, actions=np.full(length, 5, np.uint8), rewards=rewards, mission=mission,
                   outcome=SUCCESS, picked=np.array([0, 3, 0, 0], np.int8), goal=np.array([0, 3, -1, 0], np.int8))


@pytest.mark.parametrize("name,offset", [(GOTO, 1), (PICKUP, 0), (OPEN, 0)])
def test_the_generator_dataset_keeps_the_view_that_shows_the_success(name, offset):
    cfg = make_config("higher", name)
    spec = WorldSpec.of(cfg.world)
    episodes = GOTO_EPISODES if name == GOTO else real_episodes(cfg.world, 12, seed=1) if name == PICKUP else [
        opened_door(spec, length) for length in (5, 9)]  # a random policy rarely opens the door: minutes
    successes = [ep for ep in episodes if ep.outcome == SUCCESS]
    assert successes and spec.outcome_view_offset == offset
    dataset = GeneratorDataset(100, 0.5, seed=0, spec=spec)
    assert [dataset.add_episode(ep) for ep in episodes] == [ep.outcome == SUCCESS for ep in episodes]
    kept = np.stack([ep.frames[ep.length - 1 + offset] for ep in successes])
    np.testing.assert_array_equal(dataset.views[: len(successes)], kept)
    if name == GOTO:  # the last frame (after the step) is the one with the goal in front
        assert any(not (ep.frames[ep.length] == ep.frames[ep.length - 1]).all() for ep in successes)


@pytest.mark.parametrize("value", [0, 9, True, 2.5])
def test_max_per_episode_outside_one_to_eight_is_refused_by_name(value):
    with pytest.raises(ConfigError, match="relabel.max_per_episode"):
        make_config("her", "paper", **{"relabel.max_per_episode": value})


def test_the_factory_passes_max_per_episode_on():
    for value in (1, 8):
        cfg = make_config("her", GOTO, **{"relabel.max_per_episode": value})
        assert make_relabel_strategy(cfg, seed=0).max_per_episode == value
    assert make_config("her", GOTO).relabel.max_per_episode == 4


def test_copies_never_add_to_the_frames_the_update_budget_counts():
    core = Learner(make_config("her", GOTO, **{"replay.min_size": 50}))
    core.add_episodes(GOTO_EPISODES)
    frames, episodes = core.frames, core.episodes
    assert frames == sum(ep.length for ep in GOTO_EPISODES) and episodes == len(GOTO_EPISODES)
    copies = ExpertRelabel(seed=0, spec=GOTO_SPEC, max_per_episode=8).relabel(GOTO_EPISODES)
    assert len(copies) > len(FAILED)  # several per episode
    stored = len(core.replay)
    core.add_episodes(copies)
    assert (core.frames, core.episodes) == (frames, episodes)
    assert core.relabelled_episodes == len(copies) and len(core.replay) == stored + sum(c.length for c in copies)
