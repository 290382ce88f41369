"""relabel.words=expert: a learned relabeller whose generator trains and gates as HIGhER's, and whose
open gate lets through the expert's words (the ablation that keeps HIGhER's cold start and removes its
generator's mistakes)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_relabel import FEW_OBJECTS, GEN, check_copies, make_episode, mixed_batch, trained, wrong_picks  # noqa: F401

from higher_dist.config_presets import make_config
from higher_dist.learning.episode import SUCCESS
from higher_dist.learning.hindsight.generator_measure import make_pairs
from higher_dist.learning.hindsight.relabel import LearnedRelabel, make_relabel_strategy
from higher_dist.world.language import parse, parse_many

torch.set_num_threads(1)


def test_expert_words_wait_for_the_generators_gate_and_then_name_every_picked_object(trained):
    strategy = LearnedRelabel(GEN, seed=0, words="expert")
    batch, wrong = mixed_batch(seed=21)
    assert strategy.relabel(batch) == []  # shut: no pairs yet, whatever the words would be
    m = strategy.metrics()
    assert not m["relabel_gate_open"] and m["relabel_gated_off"] == len(wrong)

    rng = np.random.default_rng(3)
    views, missions, goals = make_pairs(FEW_OBJECTS, 60, "train", rng)
    strategy.observe([make_episode(v, m, SUCCESS, g, g) for v, m, g in zip(views, missions, goals)])
    assert strategy.train(100) and strategy.trainer.steps == 100  # its generator trains as HIGhER's does
    assert not strategy.trainer.gate_open and strategy.relabel(batch) == []  # 60 pairs < n_min

    strategy.trainer.load_state_dict(trained.trainer.state_dict())  # a generator whose gate has opened
    assert strategy.trainer.gate_open
    offered = wrong_picks(200, "train", seed=22) + wrong_picks(100, "heldout", seed=23)
    before = strategy.metrics()
    copies = strategy.relabel(offered)
    m = strategy.metrics()
    contradicting = m["relabel_contradicting"] - before["relabel_contradicting"]
    assert len(copies) + contradicting == len(offered) and m["relabel_unparseable"] == 0
    check_copies(copies, offered)
    named, ok = parse_many(np.stack([c.mission for c in copies]))
    # In the order offered, less those whose mission already named the picked object (contradicting).
    expected = [ep.picked for ep in offered if not np.array_equal(parse(ep.mission), ep.picked)]
    assert ok.all() and np.array_equal(named, np.stack(expected))
    assert m["relabel_accuracy"] == 1.0  # held-out objects too: the expert never guesses
    # Phrased as the expert phrases missions: several wordings of the same kind of object.
    assert len({c.mission.tobytes() for c in copies}) > len({n.tobytes() for n in named})


def test_the_generators_words_and_the_experts_differ_only_in_what_the_relabels_say(trained):
    offered = wrong_picks(120, "heldout", seed=31)
    own = LearnedRelabel(GEN, seed=0)
    expert = LearnedRelabel(GEN, seed=0, words="expert")
    for s in (own, expert):
        s.trainer.load_state_dict(trained.trainer.state_dict())
    a, b = own.relabel(offered), expert.relabel(offered)
    assert own.metrics()["relabel_accuracy"] < expert.metrics()["relabel_accuracy"] == 1.0
    assert {c.frames.tobytes() for c in a} <= {ep.frames.tobytes() for ep in offered}
    assert len(b) >= len(a)  # the generator's unparseable and contradicting outputs are dropped


def test_the_config_reaches_the_strategy_and_only_a_learned_one_takes_words():
    cfg = make_config("higher", "small", **{"relabel.words": "expert"})
    assert make_relabel_strategy(cfg, seed=0).words == "expert"
    assert make_relabel_strategy(make_config("higher", "small"), seed=0).words == "generator"
    for preset in ("her", "dqn", "noisy-her"):
        with pytest.raises(ValueError, match="relabel.words"):
            make_config(preset, "small", **{"relabel.words": "expert"})
    with pytest.raises(ValueError, match="relabel.words"):
        make_config("higher", "small", **{"relabel.words": "oracle"})

