"""The instruction language of FetchAttr: grammar, vocabulary, encoder, parser and expert describers.

Grammar: PREFIX ATTR ATTR ATTR TYPE, where PREFIX is one of `PREFIXES`, the three ATTR words are the
color, the size and the shade in any order, and TYPE (key / ball) always comes last:
"you must fetch a large very_dark green key". very_light and very_dark are single words.

A mission is a `(MISSION_LEN,)` int64 array of word ids padded with PAD, without BEG/END markers.
Attributes are `(color, type, shade, size)` indices into the global tables of `higher_dist.config`.
"""
from __future__ import annotations

import itertools

import numpy as np

from higher_dist.config import COLORS, SHADES, SIZES, TYPES
from higher_dist.world import tokens

PAD, BEG, END = tokens.PAD, tokens.BEG, tokens.END
MISSION_LEN = 10

PREFIXES = ("get a", "go get a", "fetch a", "go fetch a", "you must fetch a")
_PREFIX_WORDS = tuple(tuple(p.split()) for p in PREFIXES)
_COLOR, _TYPE, _SHADE, _SIZE = range(4)
_ATTR_TABLES = (COLORS, TYPES, SHADES, SIZES)

# Fixed vocabulary: markers, prefix words in order of first use, then every attribute word. Fixed so
# that a mission's ids mean the same thing in every process, on every world and in every checkpoint.
VOCAB: tuple[str, ...] = ("<pad>", "<beg>", "<end>") + tuple(
    dict.fromkeys(w for words in _PREFIX_WORDS for w in words)) + COLORS + SHADES + SIZES + TYPES
WORD_TO_ID: dict[str, int] = {w: i for i, w in enumerate(VOCAB)}
assert len(WORD_TO_ID) == len(VOCAB), "a word occurs twice in the vocabulary"

# word id -> (attribute, global value index), for the parser
_WORD_ATTR = {WORD_TO_ID[w]: (attr, idx) for attr, table in enumerate(_ATTR_TABLES) for idx, w in enumerate(table)}

# The three attribute words between prefix and type come in any order; an instruction's variant
# number picks a prefix and an order: variant = prefix_index * len(_ORDERS) + order_index.
_ORDERS = tuple(itertools.permutations((_COLOR, _SIZE, _SHADE)))
N_VARIANTS = len(PREFIXES) * len(_ORDERS)


def _variant_templates() -> tuple[np.ndarray, np.ndarray]:
    """Per variant, the fixed prefix word ids and which attribute fills each remaining slot (-1 none)."""
    words = np.full((N_VARIANTS, MISSION_LEN), PAD, dtype=np.int64)
    slots = np.full((N_VARIANTS, MISSION_LEN), -1, dtype=np.int64)
    for p, prefix in enumerate(_PREFIX_WORDS):
        for o, order in enumerate(_ORDERS):
            v = p * len(_ORDERS) + o
            words[v, : len(prefix)] = [WORD_TO_ID[w] for w in prefix]
            slots[v, len(prefix): len(prefix) + 4] = (*order, _TYPE)
    return words, slots


_TEMPLATE_WORDS, _TEMPLATE_SLOTS = _variant_templates()
# (attribute, global value) -> word id; padded with PAD where a table is shorter than the widest.
_ATTR_WORD_IDS = np.zeros((4, max(len(t) for t in _ATTR_TABLES)), dtype=np.int64)
for _attr, _table in enumerate(_ATTR_TABLES):
    _ATTR_WORD_IDS[_attr, : len(_table)] = [WORD_TO_ID[w] for w in _table]


def mission_tokens(attrs, variants) -> np.ndarray:
    """Missions `(n, MISSION_LEN)` for objects `attrs (n, 4)` in the given grammar variants `(n,)`."""
    attrs = np.asarray(attrs, dtype=np.int64).reshape(-1, 4)
    variants = np.asarray(variants, dtype=np.int64).reshape(-1)
    slots = _TEMPLATE_SLOTS[variants]  # (n, L): attribute that fills each position, -1 = none
    filled = np.maximum(slots, 0)
    values = np.take_along_axis(attrs, filled, axis=1)
    return np.where(slots >= 0, _ATTR_WORD_IDS[filled, values], _TEMPLATE_WORDS[variants])


def expert_tokens(attrs, rng: np.random.Generator) -> np.ndarray:
    """The expert describer: missions `(n, MISSION_LEN)` for `attrs (n, 4)`, random prefix and order."""
    attrs = np.asarray(attrs).reshape(-1, 4)
    return mission_tokens(attrs, rng.integers(N_VARIANTS, size=len(attrs)))


def describe(attrs, rng: np.random.Generator) -> str:
    """The expert describer for one object, as text."""
    return decode(mission_tokens(attrs, [rng.integers(N_VARIANTS)])[0])


def encode(text: str) -> np.ndarray:
    """Text -> `(MISSION_LEN,)` int64 word ids padded with PAD. Unknown words raise ValueError."""
    return tokens.encode(text, WORD_TO_ID, MISSION_LEN)


def _words_of(token_ids) -> list[int] | None:
    """Word ids between an optional leading BEG and the first END / PAD; None if ill-formed."""
    return tokens.word_ids(token_ids, len(VOCAB))


def decode(token_ids) -> str:
    """Word ids -> text; skips a leading BEG, stops at END or PAD. Out-of-range ids raise ValueError."""
    return tokens.decode(token_ids, VOCAB)


def prefix(token_ids) -> str | None:
    """The mission's prefix phrase ("go fetch a", ...): its words before the first attribute word; None if
    the words before it are not one of `PREFIXES`."""
    words = _words_of(token_ids) or []
    head = tuple(VOCAB[w] for w in itertools.takewhile(lambda w: w not in _WORD_ATTR, words))
    return " ".join(head) if head in _PREFIX_WORDS else None


def parse(tokens_or_text) -> np.ndarray | None:
    """An instruction (text or word ids) -> the `(4,)` int8 attributes it names, or None.

    None when the sentence names no consistent object: no valid prefix, a missing or repeated
    attribute kind, an unknown word or the type not last.
    """
    if isinstance(tokens_or_text, str):
        ids = [WORD_TO_ID.get(w, -1) for w in tokens_or_text.split()]
        if -1 in ids or any(i in (PAD, BEG, END) for i in ids):
            return None
    else:
        ids = _words_of(tokens_or_text)
        if ids is None:
            return None
    words = [VOCAB[i] for i in ids]
    for prefix in _PREFIX_WORDS:
        if tuple(words[: len(prefix)]) == prefix:
            rest = ids[len(prefix):]
            break
    else:
        return None
    if len(rest) != 4:
        return None
    attrs = np.full(4, -1, dtype=np.int8)
    for position, word_id in enumerate(rest):
        if word_id not in _WORD_ATTR:
            return None
        attr, value = _WORD_ATTR[word_id]
        if (attr == _TYPE) != (position == 3) or attrs[attr] != -1:
            return None  # the type must be last and each kind named once
        attrs[attr] = value
    return attrs


def parse_many(token_rows) -> tuple[np.ndarray, np.ndarray]:
    """Rows of word ids `(n, L)` -> (attrs `(n, 4)` int64, -1 rows where unparsed; ok `(n,)` bool)."""
    return tokens.parse_rows(token_rows, parse)


def satisfies(described, objects) -> np.ndarray:
    """Whether each object `objects (n, 4)` fits the description `described (n, 4)`: a FetchAttr
    instruction names all four attributes, so only the object itself does."""
    return (np.asarray(described, np.int64) == np.asarray(objects, np.int64)).all(axis=-1)


def noisy_attrs(attrs, p: float, space, rng: np.random.Generator) -> np.ndarray:
    """The noisy expert's view of `attrs (n, 4)`, as the paper defines it: each attribute, with
    probability p, is swapped to another of the world's values for it (`space.values(attr)`), drawn
    uniformly among the others. An attribute the world gives a single value cannot change."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"noisy_attrs: p must be in [0, 1], got {p}")
    attrs = np.asarray(attrs, dtype=np.int8).reshape(-1, 4)
    n = len(attrs)
    swap = rng.random((n, 4)) < p
    out = attrs.astype(np.int64)
    for a in range(4):
        values = np.sort(np.asarray(space.values(a), np.int64))
        k = len(values)
        if k < 2:
            continue
        position = np.searchsorted(values, out[:, a])
        if not (values[np.minimum(position, k - 1)] == out[:, a]).all():
            raise ValueError(f"noisy_attrs: attribute {a} holds values this world does not use")
        # One of the k - 1 other values, uniformly: a shift of 1..k-1 positions around the value list.
        other = values[(position + rng.integers(1, k, size=n)) % k]
        out[:, a] = np.where(swap[:, a], other, out[:, a])
    return out.astype(np.int8)


def with_markers(missions) -> np.ndarray:
    """Missions `(n, MISSION_LEN)` -> decoder targets `(n, MISSION_LEN + 2)`: BEG words END PAD..."""
    return tokens.with_markers(missions, MISSION_LEN)
