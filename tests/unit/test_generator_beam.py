"""The generator's beam search (`generator.beam_width`): the scores are the model's own log-probabilities,
width 1 is greedy decoding, and greedy words that name no object give way to the likeliest beam that does."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_relabel import FEW_OBJECTS, wrong_picks

from higher_dist.config import ConfigError, GeneratorConfig
from higher_dist.config_presets import make_config
from higher_dist.learning.hindsight.generator import GeneratorTrainer, InstructionGenerator, decoder_targets
from higher_dist.learning.hindsight.generator_data import semantic_accuracy
from higher_dist.learning.hindsight.generator_measure import make_pairs
from higher_dist.learning.hindsight.relabel import LearnedRelabel, make_relabel_strategy
from higher_dist.world.language import BEG, END, MISSION_LEN, PAD, parse_many

torch.set_num_threads(1)

SMALL = GeneratorConfig(embed_dim=8, conv_channels=(16, 16), word_embed_dim=16, hidden=64, lr=3e-3,
                        batch_size=32, capacity=2000, n_min=10, min_accuracy=0.5, val_fraction=0.2)


@pytest.fixture(scope="module")
def few_pairs_trainer():
    """A generator trained on 40 pairs: it sees the object before it knows the grammar, so some of
    its greedy outputs do not parse."""
    rng = np.random.default_rng(3)
    views, missions, _ = make_pairs(FEW_OBJECTS, 40, "train", rng)
    trainer = GeneratorTrainer(SMALL, seed=0)
    trainer.dataset.add_many(views, missions)
    trainer.train_steps(120)
    return trainer, make_pairs(FEW_OBJECTS, 256, "train", rng)


def log_probability(model: InstructionGenerator, views: torch.Tensor, words: torch.Tensor) -> torch.Tensor:
    """Teacher-forced log-probability of `words END` for each view, PAD and BEG never emitted: the
    reference the beam's running scores must equal."""
    logits = model(views, words).masked_fill(model.banned, -float("inf"))
    targets = decoder_targets(words)
    logp = F.log_softmax(logits, dim=2).gather(2, targets[..., None])[..., 0]
    return torch.where(targets != PAD, logp, torch.zeros_like(logp)).sum(dim=1)


def test_width_one_is_greedy_decoding():
    model = InstructionGenerator(SMALL).eval()
    views = torch.as_tensor(np.random.default_rng(0).integers(0, 5, size=(32, 7, 7, 4)), dtype=torch.uint8)
    words, scores = model.beam(views, 1)
    assert words.shape == (32, 1, MISSION_LEN) and scores.shape == (32, 1)
    assert torch.equal(words[:, 0], model.greedy(views))


def test_beams_are_distinct_sorted_and_scored_by_the_model(few_pairs_trainer):
    trainer, (views, _, _) = few_pairs_trainer
    model = trainer.model.eval()
    inputs = torch.as_tensor(views[:64])
    words, scores = model.beam(inputs, 6)
    assert words.shape == (64, 6, MISSION_LEN) and words.dtype == torch.int64
    assert not ((words == BEG) | (words == END)).any()
    assert (scores[:, :-1] >= scores[:, 1:] - 1e-6).all()  # likeliest first
    lengths = (words != PAD).sum(dim=2)
    finished = lengths < SMALL.max_len  # every beam here ended within the cap: its score is whole
    assert finished.all()
    for row in words:
        assert len({beam.numpy().tobytes() for beam in row}) == 6  # no beam found twice
    reference = log_probability(model, inputs.repeat_interleave(6, 0), words.reshape(-1, MISSION_LEN))
    assert torch.allclose(scores.reshape(-1), reference, atol=1e-4)


def test_unparsed_greedy_words_are_replaced_by_the_likeliest_beam_that_parses(few_pairs_trainer):
    trainer, (views, _, goals) = few_pairs_trainer
    greedy = trainer.generate(views)
    beamed = GeneratorTrainer(replace(SMALL, beam_width=8), seed=0)
    beamed.model.load_state_dict(trainer.model.state_dict())
    chosen = beamed.generate(views)
    words, _ = beamed.model.eval().beam(torch.as_tensor(views), 8)
    _, ok = parse_many(words.reshape(-1, MISSION_LEN).numpy())
    ok = ok.reshape(len(views), 8)
    greedy_ok = parse_many(greedy)[1]
    assert np.array_equal(chosen[greedy_ok], greedy[greedy_ok])  # greedy words that parse stay
    searched = ~greedy_ok & ok.any(axis=1)
    first = ok.argmax(axis=1)  # beams come likeliest first
    assert searched.sum() >= 10
    assert np.array_equal(chosen[searched], words.numpy()[np.arange(len(views)), first][searched])
    assert np.array_equal(chosen[~ok.any(axis=1)], greedy[~ok.any(axis=1)])  # nothing found: greedy words stay
    plain, searched_words = semantic_accuracy(greedy, goals), semantic_accuracy(chosen, goals)
    assert plain["parse_rate"] < 0.9  # the premise: this generator's greedy words often do not parse
    assert searched_words["parse_rate"] > plain["parse_rate"] and searched_words["exact"] > plain["exact"]
    # The gate reads the same decoding as the relabels.
    assert beamed.evaluate_pairs(views, few_pairs_trainer[1][1])["exact"] == pytest.approx(searched_words["exact"])


def test_the_relabeller_writes_the_beams_words(few_pairs_trainer):
    """Through LearnedRelabel: the same weights, with a beam, relabel more of the offered wrong picks
    (fewer outputs dropped as unparseable), and the config reaches the strategy's generator."""
    offered = wrong_picks(150, "train", seed=5)
    made = {}
    for width in (0, 8):
        strategy = LearnedRelabel(replace(SMALL, n_min=1, min_accuracy=0.0, beam_width=width), seed=0)
        strategy.trainer.load_state_dict(few_pairs_trainer[0].state_dict())
        made[width] = (len(strategy.relabel(offered)), strategy.metrics()["relabel_unparseable"])
    assert made[0][1] >= 15 and made[8][1] < made[0][1] / 3
    assert made[8][0] > made[0][0]
    cfg = make_config("higher", "small", **{"generator.beam_width": 8})
    assert make_relabel_strategy(cfg, seed=0).trainer.cfg.beam_width == 8


@pytest.mark.parametrize("value", [-1, 65, 2.5, True, "8"])
def test_a_bad_beam_width_is_refused_by_name(value):
    with pytest.raises(ConfigError, match="generator.beam_width"):
        make_config("higher", "paper", **{"generator.beam_width": value})
