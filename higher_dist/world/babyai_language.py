"""The instruction language of BabyAI's single-instruction levels: vocabulary, encoder, parser and expert
describer, for each of the three verbs a supported level uses.

A level's missions all have one verb (world/babyai_levels.py finds it: its `kind`). `BabyAILanguage(kind)`
offers the interface of `higher_dist.world.language` (FetchAttr's) for that verb; the module-level functions
are those of the pickup language.

Grammar (what minigrid's `PickupInstr`, `GoToInstr` and `OpenInstr` of an `ObjDesc(type, color, loc)` say):
    VERB ("the" | "a") [COLOR] (TYPE | "object") [LOC]
with VERB "pick up" (types key, ball, box), "go to" (key, ball, box, door) or "open" (door only), and LOC
one of "on your left", "on your right", "in front of you", "behind you". The article is "the" when exactly
one object of the level matches the description (location included), else "a".

A mission is a `(MISSION_LEN,)` int64 array of word ids padded with PAD, without BEG/END markers.
A described object is a `(4,)` int8 array `(color, type, loc, plural)`: indices into COLORS, TYPES
and LOCS, -1 where the sentence does not name that attribute ("object" = no type), and plural 1
for the article "a", 0 for "the". An achieved object (what the world records for hindsight) has the
same columns except the third: a location mask, bit i set when LOCS[i] describes the object from where
the agent started (0..15; 0 when no location word does).
"""
from __future__ import annotations

import itertools

import numpy as np

from higher_dist.world import tokens

PAD, BEG, END = tokens.PAD, tokens.BEG, tokens.END
MISSION_LEN = 10  # the longest, "pick up the purple ball in front of you", has 9 words

COLORS = ("red", "green", "blue", "purple", "yellow", "grey")  # minigrid's COLOR_TO_IDX order
TYPES = ("key", "ball", "box", "door")
DOOR = TYPES.index("door")
LOCS = ("left", "right", "front", "behind")
ATTR_NAMES = ("color", "type", "loc", "plural")
ARTICLES = ("the", "a")  # indexed by the plural column
LOC_PHRASES = ("on your left", "on your right", "in front of you", "behind you")  # by LOCS index
N_VARIANTS = 1  # one wording per description: there is no choice of prefix or word order

# Each level kind: its verb, and the types (indices into TYPES) its instructions may name. "object" (no
# type) is minigrid's word for any type; an open instruction always names a door.
KINDS = ("pickup", "goto", "open")
VERBS = {"pickup": ("pick", "up"), "goto": ("go", "to"), "open": ("open",)}
KIND_TYPES = {"pickup": (0, 1, 2), "goto": (0, 1, 2, 3), "open": (DOOR,)}

# Fixed vocabulary: ids mean the same thing in every process and in every checkpoint (words are only
# ever appended).
VOCAB: tuple[str, ...] = ("<pad>", "<beg>", "<end>", "pick", "up", "the", "a") + COLORS + TYPES[:3] + (
    "object", "on", "your", "left", "right", "in", "front", "of", "you", "behind", "go", "to", "open", "door")
WORD_TO_ID: dict[str, int] = {w: i for i, w in enumerate(VOCAB)}
assert len(WORD_TO_ID) == len(VOCAB), "a word occurs twice in the vocabulary"

_ARTICLE_IDS = {WORD_TO_ID[w]: plural for plural, w in enumerate(ARTICLES)}
_COLOR_IDS = {WORD_TO_ID[w]: i for i, w in enumerate(COLORS)}
_TYPE_IDS = {WORD_TO_ID[w]: i for i, w in enumerate(TYPES)}
_TYPE_IDS[WORD_TO_ID["object"]] = -1
_LOC_IDS = {tuple(WORD_TO_ID[w] for w in phrase.split()): i for i, phrase in enumerate(LOC_PHRASES)}
_LOC_IDS[()] = -1


def _check_attrs(attrs) -> np.ndarray:
    a = np.asarray(attrs, dtype=np.int64).reshape(-1, 4)
    highs = np.array([len(COLORS), len(TYPES), len(LOCS), 2])
    lows = np.array([-1, -1, -1, 0])
    if len(a) and ((a < lows).any() or (a >= highs).any()):
        raise ValueError(f"attributes out of range (color, type, loc, plural): {a.tolist()}")
    return a


def encode(text: str) -> np.ndarray:
    """Text -> `(MISSION_LEN,)` int64 word ids padded with PAD. Unknown words raise ValueError."""
    return tokens.encode(text, WORD_TO_ID, MISSION_LEN)


def decode(token_ids) -> str:
    """Word ids -> text; skips a leading BEG, stops at END or PAD. Out-of-range ids raise ValueError."""
    return tokens.decode(token_ids, VOCAB)


def with_markers(missions) -> np.ndarray:
    """Missions `(n, MISSION_LEN)` -> decoder targets `(n, MISSION_LEN + 2)`: BEG words END PAD..."""
    return tokens.with_markers(missions, MISSION_LEN)


LOC_MASKS = 1 << len(LOCS)  # an achieved object's location mask is in [0, LOC_MASKS)


def satisfies(described, objects) -> np.ndarray:
    """Whether each achieved object `objects (n, 4)` (colour, type, location mask, plural) fits the
    description `described (n, 4)`, as the level's verifier judges it: an unnamed colour, type or location
    (-1) admits any; a named location must be one of the object's (its mask; an object whose mask is
    unknown, -1, fits no named location). The article is not judged: the verifier accepts any object
    the description matches, whatever the level would have called it."""
    d, o = np.asarray(described, np.int64), np.asarray(objects, np.int64)
    loc_ok = (d[..., 2] == -1) | ((o[..., 2] >= 0) & ((np.maximum(o[..., 2], 0) >> np.maximum(d[..., 2], 0)) & 1 > 0))
    return (((d[..., 0] == -1) | (d[..., 0] == o[..., 0])) & ((d[..., 1] == -1) | (d[..., 1] == o[..., 1]))
            & loc_ok & (o[..., 0] >= 0) & (o[..., 1] >= 0))


class BabyAILanguage:
    """The language of one level kind ("pickup", "goto" or "open"): its verb and the types it names."""

    VOCAB, MISSION_LEN, COLORS, TYPES, LOCS = VOCAB, MISSION_LEN, COLORS, TYPES, LOCS
    ATTR_NAMES, N_VARIANTS, PAD, BEG, END = ATTR_NAMES, N_VARIANTS, PAD, BEG, END
    encode, decode, with_markers, satisfies = (staticmethod(encode), staticmethod(decode),
                                               staticmethod(with_markers), staticmethod(satisfies))

    def __init__(self, kind: str):
        if kind not in KINDS:
            raise ValueError(f"BabyAI level kind: {kind!r} is not one of {', '.join(KINDS)}")
        self.kind = kind
        self.verb = VERBS[kind]
        self.types = KIND_TYPES[kind]
        self._verb_ids = tuple(WORD_TO_ID[w] for w in self.verb)

    def __repr__(self) -> str:
        return f"BabyAILanguage({self.kind!r})"

    def _sentence_words(self, color: int, type_: int, loc: int, plural: int) -> list[str]:
        words = list(self.verb) + [ARTICLES[plural]]
        if color >= 0:
            words.append(COLORS[color])
        words.append(TYPES[type_] if type_ >= 0 else "object")
        if loc >= 0:
            words.extend(LOC_PHRASES[loc].split())
        return words

    def all_attrs(self) -> np.ndarray:
        """Every description this kind's grammar can say, `(n, 4)` int8 (color, type, loc, plural)."""
        types = self.types + ((-1,) if self.kind != "open" else ())
        rows = itertools.product(range(-1, len(COLORS)), types, range(-1, len(LOCS)), (0, 1))
        return np.array(list(rows), dtype=np.int8)

    def mission_tokens(self, attrs, variants=None) -> np.ndarray:
        """Missions `(n, MISSION_LEN)` for descriptions `attrs (n, 4)`; the inverse of `parse`.
        `variants` is accepted for the FetchAttr language's signature and ignored (one wording)."""
        a = _check_attrs(attrs)
        out = np.full((len(a), MISSION_LEN), PAD, dtype=np.int64)
        for row, (color, type_, loc, plural) in enumerate(a.tolist()):
            ids = [WORD_TO_ID[w] for w in self._sentence_words(color, type_, loc, plural)]
            out[row, : len(ids)] = ids
        return out

    def expert_tokens(self, achieved, rng: np.random.Generator | None = None,
                      name_location: bool = False) -> np.ndarray:
        """The hindsight expert: "VERB {the|a} {color} {type}" for achieved outcomes' objects `(n, 4)`, with
        the article the outcome recorded for its colour and type. name_location (a level whose missions name
        locations): add "LOC" (one of the locations the object's mask holds, drawn from `rng`) wherever one
        describes it; a location only narrows the description, so "the" stays right, while an "a" the level
        might have said as "the" stays "a". Without it `rng` is unused (kept for FetchAttr's signature)."""
        a = np.array(np.asarray(achieved, dtype=np.int64).reshape(-1, 4))
        masks = a[:, 2].tolist()
        a[:, 2] = -1
        if name_location:
            if rng is None:
                raise ValueError("expert_tokens: naming a location draws from an rng; none given")
            for row, mask in enumerate(masks):
                held = [bit for bit in range(len(LOCS)) if mask > 0 and mask >> bit & 1]
                if held:
                    a[row, 2] = held[int(rng.integers(len(held)))]
        return self.mission_tokens(a)

    def describe(self, attrs, rng: np.random.Generator | None = None) -> str:
        """The sentence for one description, as text."""
        return decode(self.mission_tokens(attrs)[0])

    def _parse_ids(self, ids: list[int]) -> np.ndarray | None:
        n = len(self._verb_ids)
        if len(ids) < n + 2 or tuple(ids[:n]) != self._verb_ids or ids[n] not in _ARTICLE_IDS:
            return None
        plural, rest = _ARTICLE_IDS[ids[n]], ids[n + 1:]
        color = _COLOR_IDS.get(rest[0], -1)
        if color >= 0:
            rest = rest[1:]
        if not rest or rest[0] not in _TYPE_IDS:
            return None
        type_, loc = _TYPE_IDS[rest[0]], _LOC_IDS.get(tuple(rest[1:]))
        if loc is None or not (type_ in self.types or (type_ == -1 and self.kind != "open")):
            return None
        return np.array([color, type_, loc, plural], dtype=np.int8)

    def parse(self, tokens_or_text) -> np.ndarray | None:
        """An instruction (text or word ids) -> its `(4,)` int8 (color, type, loc, plural), or None
        when it is not a sentence of this kind's grammar."""
        if isinstance(tokens_or_text, str):
            ids = [WORD_TO_ID.get(w, -1) for w in tokens_or_text.split()]
            if -1 in ids or any(i in (PAD, BEG, END) for i in ids):
                return None
        else:
            ids = tokens.word_ids(tokens_or_text, len(VOCAB))
            if ids is None:
                return None
        return self._parse_ids(ids)

    def parse_many(self, token_rows) -> tuple[np.ndarray, np.ndarray]:
        """Rows of word ids `(n, L)` -> (attrs `(n, 4)` int64, -1 rows where unparsed; ok `(n,)` bool)."""
        return tokens.parse_rows(token_rows, self.parse)


LANGUAGES = {kind: BabyAILanguage(kind) for kind in KINDS}
PICKUP = LANGUAGES["pickup"]

# The pickup language's functions at module level (the language of the pickup levels).
all_attrs, mission_tokens, expert_tokens = PICKUP.all_attrs, PICKUP.mission_tokens, PICKUP.expert_tokens
describe, parse, parse_many = PICKUP.describe, PICKUP.parse, PICKUP.parse_many
