"""Word ids, the same mechanics for every world's language: PAD-padded missions without markers, the
decoder's BEG ... END form, and rows parsed one by one. Each language module (world/language.py,
world/babyai_language.py) binds these to its own vocabulary and grammar."""
from __future__ import annotations

from typing import Callable

import numpy as np

PAD, BEG, END = 0, 1, 2  # the same ids in every vocabulary


def encode(text: str, word_to_id: dict[str, int], mission_len: int) -> np.ndarray:
    """Text -> `(mission_len,)` int64 word ids padded with PAD. Unknown words raise ValueError."""
    words = text.split()
    if len(words) > mission_len:
        raise ValueError(f"encode: {len(words)} words do not fit in MISSION_LEN={mission_len}: {text!r}")
    tokens = np.full(mission_len, PAD, dtype=np.int64)
    for i, word in enumerate(words):
        if word not in word_to_id or word_to_id[word] in (PAD, BEG, END):
            raise ValueError(f"encode: unknown word {word!r} in {text!r}")
        tokens[i] = word_to_id[word]
    return tokens


def word_ids(tokens, vocab_size: int) -> list[int] | None:
    """Word ids between an optional leading BEG and the first END / PAD; None if ill-formed."""
    ids = np.asarray(tokens).reshape(-1)
    if ids.dtype.kind not in "iu":
        return None
    ids = ids.tolist()
    if ids and ids[0] == BEG:
        ids = ids[1:]
    words = []
    for position, i in enumerate(ids):
        if i in (END, PAD):
            # Only padding may follow the sentence: a word after it means a malformed sequence.
            if any(j not in (PAD, END) for j in ids[position + 1:]):
                return None
            break
        if not (0 <= i < vocab_size) or i == BEG:
            return None
        words.append(i)
    return words


def decode(tokens, vocab: tuple[str, ...]) -> str:
    """Word ids -> text; skips a leading BEG, stops at END or PAD. Out-of-range ids raise ValueError."""
    ids = np.asarray(tokens).reshape(-1)
    if ids.dtype.kind not in "iu" or (ids.size and (ids.min() < 0 or ids.max() >= len(vocab))):
        raise ValueError(f"decode: token ids must be integers in [0, {len(vocab)}), got {ids.tolist()}")
    words = []
    for position, i in enumerate(ids.tolist()):
        if i == BEG and position == 0:
            continue
        if i in (END, PAD):
            break
        words.append(vocab[i])
    return " ".join(words)


def parse_rows(tokens, parse: Callable[[np.ndarray], np.ndarray | None]) -> tuple[np.ndarray, np.ndarray]:
    """Rows of word ids `(n, L)` -> (attrs `(n, 4)` int64, -1 rows where unparsed; ok `(n,)` bool)."""
    tokens = np.asarray(tokens)
    if tokens.ndim < 2:  # one mission
        tokens = tokens.reshape(1, -1)
    attrs = np.full((len(tokens), 4), -1, dtype=np.int64)
    ok = np.zeros(len(tokens), dtype=bool)
    for row, t in enumerate(tokens):
        parsed = parse(t)
        if parsed is not None:
            attrs[row], ok[row] = parsed, True
    return attrs, ok


def with_markers(missions, mission_len: int) -> np.ndarray:
    """Missions `(n, mission_len)` -> decoder targets `(n, mission_len + 2)`: BEG words END PAD..."""
    missions = np.asarray(missions, dtype=np.int64).reshape(-1, mission_len)
    out = np.full((len(missions), mission_len + 2), PAD, dtype=np.int64)
    out[:, 0] = BEG
    out[:, 1:-1] = missions
    lengths = (missions != PAD).sum(axis=1)
    out[np.arange(len(missions)), lengths + 1] = END
    return out
