"""The instruction language of BabyAI's pickup levels: vocabulary, encoder, parser and expert describer.

Same interface as `higher_dist.world.language` (FetchAttr's), so callers can use either module.

Grammar (what minigrid's `PickupInstr(ObjDesc(type, color, loc))` says):
    "pick up" ("the" | "a") [COLOR] (TYPE | "object") [LOC]
with LOC one of "on your left", "on your right", "in front of you", "behind you". The article is
"the" when exactly one object of the level matches the description, else "a".

A mission is a `(MISSION_LEN,)` int64 array of word ids padded with PAD, without BEG/END markers.
A described object is a `(4,)` int8 array `(color, type, loc, plural)`: indices into COLORS, TYPES
and LOCS, -1 where the sentence does not name that attribute ("object" = no type), and plural 1
for the article "a", 0 for "the".
"""
from __future__ import annotations

import itertools

import numpy as np

from higher_dist.world import tokens

PAD, BEG, END = tokens.PAD, tokens.BEG, tokens.END
MISSION_LEN = 10  # the longest, "pick up the purple ball in front of you", has 9 words

COLORS = ("red", "green", "blue", "purple", "yellow", "grey")  # minigrid's COLOR_TO_IDX order
TYPES = ("key", "ball", "box")
LOCS = ("left", "right", "front", "behind")
ATTR_NAMES = ("color", "type", "loc", "plural")
ARTICLES = ("the", "a")  # indexed by the plural column
LOC_PHRASES = ("on your left", "on your right", "in front of you", "behind you")  # by LOCS index
N_VARIANTS = 1  # one wording per description: there is no choice of prefix or word order

# Fixed vocabulary: ids mean the same thing in every process and in every checkpoint.
VOCAB: tuple[str, ...] = ("<pad>", "<beg>", "<end>", "pick", "up", "the", "a") + COLORS + TYPES + (
    "object", "on", "your", "left", "right", "in", "front", "of", "you", "behind")
WORD_TO_ID: dict[str, int] = {w: i for i, w in enumerate(VOCAB)}
assert len(WORD_TO_ID) == len(VOCAB), "a word occurs twice in the vocabulary"

_PREFIX = (WORD_TO_ID["pick"], WORD_TO_ID["up"])
_ARTICLE_IDS = {WORD_TO_ID[w]: plural for plural, w in enumerate(ARTICLES)}
_COLOR_IDS = {WORD_TO_ID[w]: i for i, w in enumerate(COLORS)}
_TYPE_IDS = {WORD_TO_ID[w]: i for i, w in enumerate(TYPES)}
_TYPE_IDS[WORD_TO_ID["object"]] = -1
_LOC_IDS = {tuple(WORD_TO_ID[w] for w in phrase.split()): i for i, phrase in enumerate(LOC_PHRASES)}
_LOC_IDS[()] = -1


def _sentence_words(color: int, type_: int, loc: int, plural: int) -> list[str]:
    words = ["pick", "up", ARTICLES[plural]]
    if color >= 0:
        words.append(COLORS[color])
    words.append(TYPES[type_] if type_ >= 0 else "object")
    if loc >= 0:
        words.extend(LOC_PHRASES[loc].split())
    return words


def all_attrs() -> np.ndarray:
    """Every description the grammar can say, `(n, 4)` int8 (color, type, loc, plural)."""
    rows = itertools.product(range(-1, len(COLORS)), range(-1, len(TYPES)), range(-1, len(LOCS)), (0, 1))
    return np.array(list(rows), dtype=np.int8)


def _check_attrs(attrs) -> np.ndarray:
    a = np.asarray(attrs, dtype=np.int64).reshape(-1, 4)
    highs = np.array([len(COLORS), len(TYPES), len(LOCS), 2])
    lows = np.array([-1, -1, -1, 0])
    if len(a) and ((a < lows).any() or (a >= highs).any()):
        raise ValueError(f"attributes out of range (color, type, loc, plural): {a.tolist()}")
    return a


def mission_tokens(attrs, variants=None) -> np.ndarray:
    """Missions `(n, MISSION_LEN)` for descriptions `attrs (n, 4)`; the inverse of `parse`.
    `variants` is accepted for the FetchAttr language's signature and ignored (one wording)."""
    a = _check_attrs(attrs)
    out = np.full((len(a), MISSION_LEN), PAD, dtype=np.int64)
    for row, (color, type_, loc, plural) in enumerate(a.tolist()):
        ids = [WORD_TO_ID[w] for w in _sentence_words(color, type_, loc, plural)]
        out[row, : len(ids)] = ids
    return out


def expert_tokens(picked, rng: np.random.Generator | None = None) -> np.ndarray:
    """The hindsight expert: "pick up {the|a} {color} {type}" for picked objects `(n, 4)`.
    The location is never named (where an object lies is relative to the agent's start, which the
    expert does not describe); `rng` is unused, kept for the FetchAttr language's signature."""
    a = np.array(np.asarray(picked, dtype=np.int64).reshape(-1, 4))
    a[:, 2] = -1
    return mission_tokens(a)


def describe(attrs, rng: np.random.Generator | None = None) -> str:
    """The sentence for one description, as text."""
    return decode(mission_tokens(attrs)[0])


def encode(text: str) -> np.ndarray:
    """Text -> `(MISSION_LEN,)` int64 word ids padded with PAD. Unknown words raise ValueError."""
    return tokens.encode(text, WORD_TO_ID, MISSION_LEN)


def _words_of(token_ids) -> list[int] | None:
    """Word ids between an optional leading BEG and the first END / PAD; None if ill-formed."""
    return tokens.word_ids(token_ids, len(VOCAB))


def decode(token_ids) -> str:
    """Word ids -> text; skips a leading BEG, stops at END or PAD. Out-of-range ids raise ValueError."""
    return tokens.decode(token_ids, VOCAB)


def _parse_ids(ids: list[int]) -> np.ndarray | None:
    if len(ids) < 4 or tuple(ids[:2]) != _PREFIX or ids[2] not in _ARTICLE_IDS:
        return None
    plural, rest = _ARTICLE_IDS[ids[2]], ids[3:]
    color = _COLOR_IDS.get(rest[0], -1)
    if color >= 0:
        rest = rest[1:]
    if not rest or rest[0] not in _TYPE_IDS:
        return None
    type_, loc = _TYPE_IDS[rest[0]], _LOC_IDS.get(tuple(rest[1:]))
    if loc is None:
        return None
    return np.array([color, type_, loc, plural], dtype=np.int8)


def parse(tokens_or_text) -> np.ndarray | None:
    """An instruction (text or word ids) -> its `(4,)` int8 (color, type, loc, plural), or None
    when it is not a sentence of the pickup grammar."""
    if isinstance(tokens_or_text, str):
        ids = [WORD_TO_ID.get(w, -1) for w in tokens_or_text.split()]
        if -1 in ids or any(i in (PAD, BEG, END) for i in ids):
            return None
    else:
        ids = _words_of(tokens_or_text)
        if ids is None:
            return None
    return _parse_ids(ids)


def parse_many(token_rows) -> tuple[np.ndarray, np.ndarray]:
    """Rows of word ids `(n, L)` -> (attrs `(n, 4)` int64, -1 rows where unparsed; ok `(n,)` bool)."""
    return tokens.parse_rows(token_rows, parse)


def with_markers(missions) -> np.ndarray:
    """Missions `(n, MISSION_LEN)` -> decoder targets `(n, MISSION_LEN + 2)`: BEG words END PAD..."""
    return tokens.with_markers(missions, MISSION_LEN)


def satisfies(described, objects) -> np.ndarray:
    """Whether each object `objects (n, 4)` (colour, type, ...) fits the description `described (n, 4)`,
    as the level's verifier judges a pickup: an unnamed colour or type (-1) admits any. The location
    and the article are not properties of the object (they depend on where the agent started and on
    the other objects), so they are not judged."""
    d, o = np.asarray(described, np.int64), np.asarray(objects, np.int64)
    return (((d[..., 0] == -1) | (d[..., 0] == o[..., 0])) & ((d[..., 1] == -1) | (d[..., 1] == o[..., 1]))
            & (o[..., 0] >= 0) & (o[..., 1] >= 0))
