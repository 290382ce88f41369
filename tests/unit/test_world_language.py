"""The instruction language: vocabulary, grammar round trip, parser, expert and noisy expert."""
import numpy as np
import pytest

from higher_dist.config import COLORS, SHADES, SIZES, TYPES, WorldConfig
from higher_dist.config_presets import small_world
from higher_dist.world.language import (BEG, END, MISSION_LEN, N_VARIANTS, PAD, PREFIXES, VOCAB, WORD_TO_ID,
                                        decode, describe, encode, expert_tokens, mission_tokens, noisy_attrs,
                                        parse, with_markers)
from higher_dist.world.objects import ObjectSpace

ALL_OBJECTS = ObjectSpace(WorldConfig()).all_objects


def test_vocabulary_is_fixed_with_markers_first():
    assert (PAD, BEG, END) == (0, 1, 2) and MISSION_LEN == 10
    assert len(set(VOCAB)) == len(VOCAB)
    for word in (*COLORS, *SHADES, *SIZES, *TYPES, "you", "must", "fetch", "go", "get", "a"):
        assert word in WORD_TO_ID and VOCAB[WORD_TO_ID[word]] == word
    assert "very_light" in VOCAB and "very" not in VOCAB  # single words


def test_round_trip_for_all_300_objects_every_prefix_and_order():
    n = len(ALL_OBJECTS)
    seen_prefixes, seen_orders = set(), set()
    for variant in range(N_VARIANTS):
        tokens = mission_tokens(ALL_OBJECTS, np.full(n, variant))
        assert tokens.shape == (n, MISSION_LEN) and tokens.dtype == np.int64
        marked = with_markers(tokens)  # the decoder's BEG ... END form
        for attrs, row, marked_row in zip(ALL_OBJECTS.tolist(), tokens, marked):
            text = decode(row)
            assert encode(text).tolist() == row.tolist()
            assert parse(row).tolist() == attrs
            assert parse(text).tolist() == attrs
            assert parse(marked_row).tolist() == attrs
        prefix = next(p for p in sorted(PREFIXES, key=len, reverse=True) if text.startswith(p + " "))
        words = text[len(prefix):].split()
        assert words[-1] == TYPES[attrs[1]]
        seen_prefixes.add(prefix)
        seen_orders.add(tuple("c" if w in COLORS else "s" if w in SHADES else "z" for w in words[:3]))
    assert seen_prefixes == set(PREFIXES)
    assert len(seen_orders) == 6


def test_example_sentence_of_the_paper():
    attrs = parse("you must fetch a large very_dark green key")
    assert attrs.tolist() == [COLORS.index("green"), 0, SHADES.index("very_dark"), SIZES.index("large")]
    assert attrs.dtype == np.int8


def test_expert_uses_random_prefixes_and_orders_but_always_the_right_object():
    rng = np.random.default_rng(0)
    attrs = np.repeat(ALL_OBJECTS[17:18], 400, axis=0)
    tokens = expert_tokens(attrs, rng)
    texts = {decode(t) for t in tokens}
    assert len(texts) == N_VARIANTS  # 400 draws of 30 equally likely wordings: all appear
    assert all(np.array_equal(parse(t), ALL_OBJECTS[17]) for t in tokens)
    text = describe(ALL_OBJECTS[5], rng)
    assert isinstance(text, str) and np.array_equal(parse(text), ALL_OBJECTS[5])


@pytest.mark.parametrize("sentence", [
    "get a red large key",  # missing shade
    "get a red blue large key",  # two colors, no shade
    "get a red neutral large small key",  # too many words
    "get a red neutral key large",  # type not last
    "get a key red neutral large",
    "get a red neutral large pink key",  # unknown word
    "red neutral large key",  # no prefix
    "fetch red neutral large key",  # broken prefix
    "go a red neutral large key",
    "get a red neutral large ball ball",
    "get a red neutral a large key",
    "get a",
    "",
])
def test_parser_rejects_sentences_naming_no_consistent_object(sentence):
    assert parse(sentence) is None


def test_parser_rejects_malformed_token_sequences():
    good = encode("fetch a red neutral large key")
    assert parse(good) is not None
    word_after_end = good.copy()
    word_after_end[6] = WORD_TO_ID["red"]
    assert parse(word_after_end) is None
    out_of_range = good.copy()
    out_of_range[2] = len(VOCAB)
    assert parse(out_of_range) is None
    beg_inside = good.copy()
    beg_inside[3] = BEG
    assert parse(beg_inside) is None
    assert parse(np.array([0.5, 1.0])) is None
    assert parse(np.zeros(MISSION_LEN, dtype=np.int64)) is None


def test_encode_and_decode_errors_are_clear():
    with pytest.raises(ValueError, match="unknown word"):
        encode("fetch a pink key")
    with pytest.raises(ValueError, match="MISSION_LEN"):
        encode("get a " * 6)
    with pytest.raises(ValueError, match="token ids"):
        decode(np.array([3, 99]))


def test_with_markers_gives_decoder_targets():
    row = encode("get a red neutral large key")
    target = with_markers(row)[0]
    assert target.shape == (MISSION_LEN + 2,)
    assert target[0] == BEG and target[7] == END and (target[8:] == PAD).all()
    np.testing.assert_array_equal(target[1:7], row[:6])


def test_noisy_expert_swaps_each_attribute_to_another_value_with_probability_p():
    space = ObjectSpace(WorldConfig())
    rng = np.random.default_rng(1)
    n, p = 40_000, 0.3
    attrs = space.train_objects[rng.integers(len(space.train_objects), size=n)]
    noisy = noisy_attrs(attrs, p, space, rng)
    assert noisy.shape == (n, 4) and noisy.dtype == np.int8
    for a in range(4):
        changed = (noisy[:, a] != attrs[:, a]).mean()
        assert abs(changed - p) < 0.012, (a, changed, p)  # ~5 standard deviations
        assert set(noisy[:, a].tolist()) <= set(space.values(a).tolist())
    # All four attributes right: (1 - p)^4, the paper's rate (resampling would give more).
    all_right = (noisy == attrs).all(axis=1).mean()
    assert abs(all_right - (1 - p) ** 4) < 0.012, all_right
    np.testing.assert_array_equal(noisy_attrs(attrs, 0.0, space, rng), attrs)
    # At p = 1 every attribute changes, to each other value about equally often.
    swapped = noisy_attrs(attrs, 1.0, space, rng)
    assert (swapped != attrs).all()
    reds = swapped[attrs[:, 0] == attrs[0, 0], 0]
    counts = np.unique(reds, return_counts=True)[1]
    assert len(counts) == len(space.values(0)) - 1 and counts.min() > 0.8 * counts.mean()


def test_noisy_expert_stays_within_the_world_values():
    space = ObjectSpace(small_world())
    rng = np.random.default_rng(2)
    attrs = np.repeat(space.train_objects[:1], 2000, axis=0)
    noisy = noisy_attrs(attrs, 1.0, space, rng)
    assert set(noisy[:, 2].tolist()) == {2} and set(noisy[:, 3].tolist()) == {2}
    assert (noisy[:, 0] != attrs[:, 0]).all()  # two colors: a swap always lands on the other one
    with pytest.raises(ValueError, match="p must be"):
        noisy_attrs(attrs, 1.5, space, rng)


def test_describer_is_deterministic_under_a_seed():
    a = expert_tokens(ALL_OBJECTS, np.random.default_rng(9))
    b = expert_tokens(ALL_OBJECTS, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, expert_tokens(ALL_OBJECTS, np.random.default_rng(10)))
