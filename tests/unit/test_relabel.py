"""Relabel strategies: which episodes are relabelled, how, and what the learned one may read."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from higher_dist.learning.hindsight.generator_measure import make_pairs
from higher_dist.config import GeneratorConfig, WorldConfig
from higher_dist.config_presets import make_config
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode
from higher_dist.learning.hindsight.relabel import (ExpertRelabel, LearnedRelabel, NoisyExpertRelabel, RelabelStrategy,
                                          make_relabel_strategy)
from higher_dist.rundir import RunDir
from higher_dist.world.language import VOCAB, expert_tokens, parse
from higher_dist.world.objects import ObjectSpace
from support.tripwire import Tripwire

torch.set_num_threads(1)

FEW_OBJECTS = WorldConfig(name="few", room_size=6, n_objects=4, colors=("red", "green", "blue"),
                          shades=("light", "dark"), sizes=("tiny", "giant"), heldout_count=6)
GEN = GeneratorConfig(embed_dim=8, conv_channels=(16, 16), word_embed_dim=16, hidden=64, lr=3e-3,
                      batch_size=32, capacity=2000, n_min=100, min_accuracy=0.8,
                      eval_every_updates=100)


def make_episode(view, mission, outcome, picked, goal, relabelled=False, length=3) -> Episode:
    frames = np.zeros((length + 1,) + np.shape(view), np.uint8)
    frames[length - 1] = view
    rewards = np.zeros(length, np.float32)
    rewards[-1] = 1.0 if outcome == SUCCESS else 0.0
    return Episode(frames=frames, actions=np.zeros(length, np.uint8), rewards=rewards,
                   mission=np.asarray(mission, np.int64), outcome=outcome, picked=picked, goal=goal,
                   relabelled=relabelled)


def wrong_picks(n: int, goal_set: str, seed: int) -> list[Episode]:
    """Wrong-pick episodes: the picked object is in front in the last view, the goal is another one."""
    rng = np.random.default_rng(seed)
    views, _, picked = make_pairs(FEW_OBJECTS, n, goal_set, rng)
    goals = ObjectSpace(FEW_OBJECTS).all_objects[rng.integers(24, size=n)]
    missions = expert_tokens(goals, rng)
    return [make_episode(v, m, WRONG_PICK, p.copy(), g.copy()) for v, m, p, g in zip(views, missions, picked, goals)]


def mixed_batch(seed: int = 0) -> tuple[list[Episode], list[Episode]]:
    """Successes, time-outs and already relabelled copies around 20 wrong picks; returns (all, wrong)."""
    wrong = wrong_picks(20, "train", seed)
    others = [replace(wrong[0], outcome=SUCCESS), replace(wrong[1], outcome=TIMEOUT,
                                                          picked=np.full(4, -1, np.int8), pick_step=-1),
              wrong[2].relabel(wrong[2].mission)]
    return others[:2] + wrong + others[2:], wrong


@pytest.fixture(scope="module")
def trained() -> LearnedRelabel:
    """A learned relabeller trained on 400 successful episodes; its gate has opened."""
    strategy = LearnedRelabel(GEN, seed=0)
    rng = np.random.default_rng(0)
    views, missions, goals = make_pairs(FEW_OBJECTS, 400, "train", rng)
    strategy.observe([make_episode(v, m, SUCCESS, g, g) for v, m, g in zip(views, missions, goals)])
    for _ in range(5):
        strategy.train(100)  # evaluated after each 100 updates (eval_every_updates=100)
    assert strategy.trainer.gate_open, strategy.metrics()
    return strategy


def check_copies(copies: list[Episode], originals: list[Episode]) -> None:
    ids = {id(ep) for ep in originals}
    for c in copies:
        assert c.relabelled and c.outcome == WRONG_PICK and c.rewards[-1] == 1.0
        assert (c.rewards[:-1] == 0).all() and id(c) not in ids
    for ep in originals:
        assert not ep.relabelled and ep.rewards[-1] == 0.0  # originals untouched


def test_none_relabels_nothing():
    batch, wrong = mixed_batch()
    strategy = RelabelStrategy(seed=0)
    strategy.observe(batch)
    assert strategy.relabel(batch) == [] and strategy.train(100) == {}
    assert strategy.metrics()["relabel_considered"] == len(wrong) and strategy.metrics()["relabel_accuracy"] is None


def test_expert_relabels_every_wrong_pick_correctly_and_nothing_else():
    batch, wrong = mixed_batch()
    strategy = ExpertRelabel(seed=0)
    copies = strategy.relabel(batch)
    assert len(copies) == len(wrong)
    check_copies(copies, wrong)
    for c, ep in zip(copies, wrong):
        assert np.array_equal(parse(c.mission), ep.picked)
        assert np.array_equal(c.frames, ep.frames)
    assert len({tuple(c.mission[:2]) for c in copies}) > 1  # random prefixes and orders
    m = strategy.metrics()
    assert m["relabels_made"] == len(wrong) and m["relabel_accuracy"] == 1.0


def test_noisy_expert_changes_each_attribute_at_rate_p():
    space = ObjectSpace(WorldConfig())
    p, n = 0.3, 4000
    rng = np.random.default_rng(0)
    picked = space.all_objects[rng.integers(len(space.all_objects), size=n)]
    view = np.zeros((7, 7, 4), np.uint8)
    episodes = [make_episode(view, np.zeros(10, np.int64), WRONG_PICK, a, a) for a in picked]
    strategy = NoisyExpertRelabel(space, p, seed=1)
    copies = strategy.relabel(episodes)
    assert len(copies) == n
    described = np.stack([parse(c.mission) for c in copies])
    changed = (described != picked).mean(axis=0)
    expected = np.full(4, p)
    assert np.allclose(changed, expected, atol=0.03), (changed, expected)
    assert strategy.metrics()["relabel_accuracy_total"] == pytest.approx((described == picked).all(axis=1).mean())


def test_learned_relabels_nothing_while_the_gate_is_closed():
    strategy = LearnedRelabel(GEN, seed=0)
    batch, wrong = mixed_batch()
    rng = np.random.default_rng(1)
    views, missions, goals = make_pairs(FEW_OBJECTS, GEN.n_min - 1, "train", rng)
    strategy.observe([make_episode(v, m, SUCCESS, g, g) for v, m, g in zip(views, missions, goals)])
    assert len(strategy.trainer.dataset) == GEN.n_min - 1
    assert strategy.relabel(batch) == []
    m = strategy.metrics()
    assert not m["relabel_gate_open"] and m["relabel_gated_off"] == len(wrong) and m["relabels_made"] == 0
    # Relabelled copies and failures never enter the generator's dataset.
    strategy.observe(batch)
    assert len(strategy.trainer.dataset) == GEN.n_min - 1 + 1  # the one success of the batch


def test_learned_with_gate_open_relabels_wrong_picks_only(trained):
    batch, wrong = mixed_batch(seed=5)
    before = trained.metrics()
    copies = trained.relabel(batch)
    m = trained.metrics()
    dropped = m["relabel_unparseable"] - before["relabel_unparseable"] + m["relabel_contradicting"] - before["relabel_contradicting"]
    assert len(copies) + dropped == len(wrong)
    assert len(copies) >= 0.9 * len(wrong)
    check_copies(copies, wrong)
    frames_of = {ep.frames.tobytes() for ep in wrong}
    assert all(c.frames.tobytes() in frames_of for c in copies)
    assert all(parse(c.mission) is not None for c in copies)
    # Scored against the picked object for the dashboard: mostly right on training objects.
    new = m["relabels_made"] - before["relabels_made"]
    assert new == len(copies)
    assert m["relabel_accuracy"] >= 0.8 and m["relabel_dataset_size"] == 400 and m["generator_val_accuracy"] >= 0.8


def test_learned_drops_and_counts_relabels_that_name_the_failed_goal(trained):
    # Wrong picks whose mission names the object in front: the generator (accurate on training
    # objects) describes exactly the goal the episode failed, which would store the same transitions
    # with reward 1 beside the original's reward 0.
    wrong = wrong_picks(30, "train", seed=9)
    rng = np.random.default_rng(9)
    told = [replace(ep, mission=expert_tokens(ep.picked[None], rng)[0]) for ep in wrong]
    before = trained.metrics()["relabel_contradicting"]
    copies = trained.relabel(told)
    m = trained.metrics()
    assert m["relabel_contradicting"] - before >= 0.8 * len(told)
    for c in copies:  # whatever got through names something other than the mission
        original = next(ep for ep in told if ep.frames.tobytes() == c.frames.tobytes())
        assert not np.array_equal(parse(c.mission), parse(original.mission))
    # The ordinary wrong picks of the same views (missions naming other objects) still get relabelled.
    assert len(trained.relabel(wrong)) >= 0.8 * len(wrong)




def test_learned_never_reads_picked_or_goal_to_relabel(trained, monkeypatch):
    wrong = wrong_picks(12, "heldout", seed=7)
    reference = [c.mission for c in trained.relabel(wrong)]
    # 1. Garbage ground truth gives the same relabels.
    garbage = [replace(ep, picked=np.array([5, 1, 0, 4], np.int8), goal=np.array([0, 0, 0, 0], np.int8))
               for ep in wrong]
    assert [c.mission.tolist() for c in trained.relabel(garbage)] == [m.tolist() for m in reference]
    # 2. Ground truth that cannot be read at all: only the after-the-fact scorer would touch it.
    scored = []
    monkeypatch.setattr(trained, "_score", lambda originals, attrs: scored.append(len(originals)))
    blind = [replace(ep, picked=Tripwire(), goal=Tripwire()) for ep in wrong]
    copies = trained.relabel(blind)
    assert [c.mission.tolist() for c in copies] == [m.tolist() for m in reference]
    assert scored == [len(copies)]


def test_learned_checkpoint_round_trip(trained, tmp_path):
    # Through the run directory's checkpoint format (torch.load with weights_only=True).
    run_dir = RunDir(tmp_path)
    run_dir.save_checkpoint("relabeler", trained.state_dict())
    clone = LearnedRelabel(GEN, seed=42)
    clone.load_state_dict(run_dir.load_checkpoint("relabeler"))
    wrong = wrong_picks(8, "train", seed=9)
    assert [c.mission.tolist() for c in clone.relabel(wrong)] == [c.mission.tolist() for c in trained.relabel(wrong)]
    for key in ("relabel_dataset_size", "generator_val_accuracy", "generator_train_steps", "relabel_gate_open"):
        assert clone.metrics()[key] == trained.metrics()[key]
    with pytest.raises(ValueError):
        ExpertRelabel(seed=0).load_state_dict(trained.state_dict())


def test_factory_builds_each_preset_strategy():
    kinds = {"dqn": RelabelStrategy, "reward": RelabelStrategy, "her": ExpertRelabel,
             "noisy-her": NoisyExpertRelabel, "higher": LearnedRelabel}
    for preset, kind in kinds.items():
        strategy = make_relabel_strategy(make_config(preset, "small"), seed=0)
        assert type(strategy) is kind, preset
    noisy = make_relabel_strategy(make_config("noisy-her", "small"), seed=0)
    assert noisy.p == 0.2
    learned = make_relabel_strategy(make_config("higher", "small"), seed=0)
    assert learned.cfg.n_min == 100


def test_a_fetchattr_failure_gives_one_copy_whatever_max_per_episode_allows():
    # A FetchAttr pick ends its episode: one outcome, so one copy at most, ending where the original does.
    batch, wrong = mixed_batch(seed=3)
    for most in (1, 8):
        copies = ExpertRelabel(seed=0, max_per_episode=most).relabel(batch)
        assert len(copies) == len(wrong)
        assert all(c.length == ep.length and c.n_outcomes == 1 for c, ep in zip(copies, wrong))


def test_relabel_accuracy_is_over_the_recent_window_and_the_total_is_reported_beside_it():
    from higher_dist.learning.hindsight.relabel import RECENT_RELABELS
    space = ObjectSpace(WorldConfig())
    rng = np.random.default_rng(2)
    view = np.zeros((7, 7, 4), np.uint8)

    def batch(n):
        picked = space.all_objects[rng.integers(len(space.all_objects), size=n)]
        return [make_episode(view, np.zeros(10, np.int64), WRONG_PICK, a, a) for a in picked]

    strategy = NoisyExpertRelabel(space, 1.0, seed=3)  # every attribute noised: mostly wrong
    strategy.relabel(batch(1500))
    early = strategy.metrics()
    assert early["relabel_accuracy"] < 0.3
    strategy.p = 0.0  # a relabeller that has become exact
    strategy.relabel(batch(RECENT_RELABELS))
    m = strategy.metrics()
    assert m["relabel_accuracy"] == 1.0  # the window holds only the exact relabels
    assert m["relabel_accuracy_total"] == pytest.approx(
        (early["relabel_accuracy_total"] * 1500 + RECENT_RELABELS) / (1500 + RECENT_RELABELS))
    assert m["relabel_accuracy_total"] < 0.7
    # The window survives a checkpoint.
    restored = NoisyExpertRelabel(space, 0.0, seed=3)
    restored.load_state_dict(strategy.state_dict())
    assert restored.metrics()["relabel_accuracy"] == 1.0


def test_generator_accuracy_is_unknown_before_its_first_evaluation_and_dated_after_it():
    strategy = LearnedRelabel(GEN, seed=0)
    rng = np.random.default_rng(4)
    views, missions, goals = make_pairs(FEW_OBJECTS, 200, "train", rng)
    strategy.observe([make_episode(v, m, SUCCESS, g, g) for v, m, g in zip(views, missions, goals)])
    assert strategy.metrics()["generator_val_accuracy"] is None
    strategy.train(100)  # evaluated after 100 updates (eval_every_updates=100)
    size_then = strategy.metrics()["relabel_dataset_size"]
    views, missions, goals = make_pairs(FEW_OBJECTS, 100, "train", rng)
    strategy.observe([make_episode(v, m, SUCCESS, g, g) for v, m, g in zip(views, missions, goals)])
    m = strategy.metrics()
    assert m["generator_val_accuracy"] is not None and m["generator_val_at_pairs"] == size_then < m["relabel_dataset_size"]


def test_rephrased_relabels_name_the_greedy_object_in_varied_words(trained, monkeypatch):
    """generator.decoding=rephrase, through the relabel path: one failure offered many times is relabelled
    with the object the greedy words name every time, in more than one phrasing (greedy: always one)."""
    failure = wrong_picks(1, "train", seed=9)[0]
    batch = [replace(failure) for _ in range(48)]
    monkeypatch.setattr(trained, "cfg", replace(GEN, decoding="greedy"))
    greedy = trained.relabel(batch)
    monkeypatch.setattr(trained, "cfg", replace(GEN, decoding="rephrase"))
    rephrased = trained.relabel(batch)
    assert len(greedy) == len(rephrased) == len(batch)
    check_copies(rephrased, batch)
    assert len({c.mission.tobytes() for c in greedy}) == 1
    assert len({c.mission.tobytes() for c in rephrased}) >= 3
    meaning = parse(greedy[0].mission)
    assert all(np.array_equal(parse(c.mission), meaning) for c in rephrased)


def test_relabels_the_generator_is_unsure_of_are_dropped_and_counted():
    """generator.min_agreement: a relabel whose object too few of the generator's draws name is dropped
    and counted as unsure; every candidate is relabelled or dropped for one counted reason, and what is
    kept is righter than what an unfiltered generator of the same weights writes."""
    cfg = replace(GEN, min_accuracy=0.0, agreement_draws=8, min_agreement=0.75)
    strategy = LearnedRelabel(cfg, seed=0)
    rng = np.random.default_rng(3)
    views, missions, goals = make_pairs(FEW_OBJECTS, 300, "train", rng)
    strategy.observe([make_episode(v, m, SUCCESS, g, g) for v, m, g in zip(views, missions, goals)])
    strategy.train(300)  # a generator still unsure of some attributes of held-out objects
    wrong = wrong_picks(200, "heldout", seed=4)
    copies = strategy.relabel(wrong)
    m = strategy.metrics()
    assert m["relabel_unsure"] > 0
    assert len(copies) + m["relabel_unparseable"] + m["relabel_unsure"] + m["relabel_contradicting"] == len(wrong)
    check_copies(copies, wrong)
    unfiltered = LearnedRelabel(replace(cfg, agreement_draws=0, min_agreement=0.0), seed=0)
    unfiltered.load_state_dict(strategy.state_dict())
    unfiltered.relabel(wrong)
    assert m["relabel_accuracy"] > unfiltered.metrics()["relabel_accuracy"]
    restored = LearnedRelabel(cfg, seed=1)
    restored.load_state_dict(strategy.state_dict())
    assert restored.metrics()["relabel_unsure"] == m["relabel_unsure"]


def test_agreement_settings_are_refused_when_they_cannot_mean_anything():
    ok = make_config("higher", "small", **{"generator.agreement_draws": 8, "generator.min_agreement": 0.75,
                                          "generator.decoding": "rephrase"})
    assert make_relabel_strategy(ok, seed=0).cfg.agreement_draws == 8
    for bad in ({"generator.agreement_draws": -1}, {"generator.agreement_draws": 65},
                {"generator.agreement_draws": 2.5}, {"generator.agreement_draws": True},
                {"generator.min_agreement": 0.5},  # a share of no draws
                {"generator.agreement_draws": 8, "generator.min_agreement": 1.5},
                {"generator.agreement_draws": 8, "generator.decoding": "sample"}):
        field = "generator.min_agreement" if set(bad) == {"generator.min_agreement"} or bad.get(
            "generator.min_agreement", 0) > 1 else "generator.agreement_draws"
        with pytest.raises(ValueError, match=field):
            make_config("higher", "small", **bad)
