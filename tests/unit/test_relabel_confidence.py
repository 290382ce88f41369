"""The generator's confidence in the values it names, and the relabels dropped under generator.min_confidence."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from higher_dist.config import ConfigError
from higher_dist.config_presets import make_config
from higher_dist.learning.hindsight.generator import inference_batch
from higher_dist.learning.hindsight.relabel import LearnedRelabel
from higher_dist.world import babyai_language, language
from higher_dist.world.language import END, PAD, parse_many
from test_relabel import GEN, trained, wrong_picks  # noqa: F401  (trained is a fixture)

torch.set_num_threads(1)


def reference_confidence(model, views: np.ndarray, words: np.ndarray) -> np.ndarray:
    """numpy: teacher-force the decoded words, then at each word naming a value take its probability
    over its attribute's values' summed probability; a row's least share, 1 where it names none."""
    missions = torch.as_tensor(words)
    with torch.no_grad():
        logits = model(torch.as_tensor(views), missions).numpy().astype(np.float64)
    logits[:, :, [PAD, language.BEG]] = -np.inf
    probs = np.exp(logits - logits.max(axis=2, keepdims=True))
    probs /= probs.sum(axis=2, keepdims=True)
    kinds = np.asarray(language.WORD_KINDS)
    out = np.ones(len(words))
    for row, sentence in enumerate(words):
        for t, word in enumerate(sentence):
            if word == PAD:
                break
            if kinds[word] >= 0:
                share = probs[row, t, word] / probs[row, t, kinds == kinds[word]].sum()
                out[row] = min(out[row], share)
    return out


def test_each_language_names_the_attribute_of_every_value_word():
    for module, values in ((language, (language.COLORS, language.TYPES, language.SHADES, language.SIZES)),
                           (babyai_language, (babyai_language.COLORS, babyai_language.TYPES + ("object",),
                                              babyai_language.LOCS, babyai_language.ARTICLES))):
        assert len(module.WORD_KINDS) == len(module.VOCAB)
        for kind, words in enumerate(values):
            assert {module.VOCAB[i] for i, k in enumerate(module.WORD_KINDS) if k == kind} == set(words)
    assert babyai_language.LANGUAGES["goto"].WORD_KINDS == babyai_language.WORD_KINDS


def test_confidence_matches_a_numpy_reference_of_the_teacher_forced_probabilities(trained):  # noqa: F811
    model = trained.trainer.model.eval()
    views = np.stack([ep.frames[-2] for ep in wrong_picks(24, "heldout", seed=3)])
    words, confidence = model.greedy_with_confidence(torch.as_tensor(views))
    words, confidence = words.numpy(), confidence.numpy()
    ended = (words == PAD).any(axis=1)  # rows cut at the mission length have steps the words do not show
    assert ended.sum() >= 20
    expected = reference_confidence(model, views[ended], words[ended])
    np.testing.assert_allclose(confidence[ended], expected, rtol=1e-4, atol=1e-6)
    assert ((confidence > 0) & (confidence <= 1)).all()
    # The trainer's numpy path pads to a fixed batch and gives the same numbers.
    tokens, sure = trained.trainer.describe(views)
    assert inference_batch(len(views)) > len(views)
    np.testing.assert_array_equal(tokens, words)
    np.testing.assert_allclose(sure, confidence, rtol=1e-5)
    assert not (tokens == END).any()


def test_relabels_under_min_confidence_are_dropped_and_counted(trained):  # noqa: F811
    wrong = wrong_picks(40, "heldout", seed=11)  # unseen objects: the generator is unsure of some
    views = np.stack([ep.frames[-2] for ep in wrong])
    tokens, confidence = trained.trainer.describe(views)
    _, ok = parse_many(tokens)
    threshold = float(np.median(confidence[ok]))
    unsure = ok & (confidence < threshold)
    assert 0 < unsure.sum() < ok.sum()
    strict = LearnedRelabel(replace(GEN, min_confidence=threshold), seed=0)
    strict.load_state_dict(trained.state_dict())
    copies = strict.relabel(wrong)
    m = strict.metrics()
    assert m["relabel_unsure"] == int(unsure.sum())
    kept_views = {views[i].tobytes() for i in np.flatnonzero(ok & ~unsure)}
    assert {c.frames[-2].tobytes() for c in copies} <= kept_views
    assert len(copies) + m["relabel_unsure"] + m["relabel_unparseable"] + m["relabel_contradicting"] == len(wrong)
    # At 0 (the default) nothing is dropped for its confidence.
    assert trained.metrics()["relabel_unsure"] == 0
    trained.relabel(wrong)
    assert trained.metrics()["relabel_unsure"] == 0
    # The count survives a checkpoint.
    clone = LearnedRelabel(replace(GEN, min_confidence=threshold), seed=1)
    clone.load_state_dict(strict.state_dict())
    assert clone.metrics()["relabel_unsure"] == m["relabel_unsure"]


@pytest.mark.parametrize("value", [-0.1, 1.0, 1.5])
def test_a_min_confidence_outside_zero_to_one_is_refused_by_name(value):
    with pytest.raises(ConfigError, match="generator.min_confidence"):
        make_config("higher", **{"generator.min_confidence": value})
