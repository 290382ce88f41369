"""The declarative schema of the higher-dist wire protocol: every message type, its header fields and its arrays.

The codec (`codec.py`) reads these tables and nothing else, so adding a message type is one `MessageSpec`
entry in `_SPECS`. The checks of header field values live here too, next to the field kinds they define, with
`WireError`, the one exception every validation failure raises. Limits are deliberately tight: a peer that
declares a size outside them is refused before any memory is touched, which is what keeps a corrupt or hostile
message from costing more than its bytes.

Value ranges (view channels, actions, outcomes, attribute indices) come from `world.spec`, the one statement
of the world's encodings. What depends on the run's own world (its view size, mission length, vocabulary, the
attribute values it uses) is checked against its `WorldSpec` by `episodes.unpack_episodes`; the schema only
caps what no world can exceed.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Union

import numpy as np

from higher_dist.world import spec as world_spec

PROTOCOL_VERSION = 2

REASONS = (
    "bad_frames",  # not a list of byte buffers
    "bad_msgpack",  # header is not valid msgpack
    "header",  # header is not a map with the expected keys and types
    "version",  # schema version differs from ours
    "unknown_type",
    "field",  # missing, extra or ill-typed header field
    "frame_count",  # truncated or extra frames, or one-frame/multipart form not matching the type
    "dtype",
    "shape",  # rank or dimension outside the schema, shape vs byte length, inconsistent shared dims
    "size",  # declared or actual byte sizes over the caps or not matching the frame
    "range",  # a value outside its allowed range
    "nan",  # NaN or infinity where numbers must be finite
)


class WireError(ValueError):
    """An invalid message. `reason` is one of REASONS, fit for counters; `detail` is for humans.

    For reason "version", `peer_version` is the version the peer speaks, so that the learner can answer
    a hello from another version with a clear `refuse` instead of silence.
    """

    def __init__(self, reason: str, detail: str = "", peer_version: int | None = None):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail
        self.peer_version = peer_version


# Size caps. A frame larger than MAX_FRAME_BYTES never reaches Python: sockets.make_socket sets MAXMSGSIZE.
MAX_ARRAY_BYTES = 64 << 20  # one array (one raw frame)
MAX_PAYLOAD_BYTES = 64 << 20  # all arrays of one message together
MAX_HEADER_BYTES = 1 << 20  # the msgpack header (a config dict is a few KiB)
MAX_FRAME_BYTES = MAX_PAYLOAD_BYTES + MAX_HEADER_BYTES + 64  # one-frame weights: prefix + header + payload
MAX_ARRAYS = 512  # arrays in one message (a Q-network state dict has a few dozen)
MAX_NDIM = 6
MAX_DIM = 1 << 28  # any single dimension; real limits per array are in the specs below

# Limits handed to msgpack.unpackb; anything larger in a header is an attack or a bug.
MSGPACK_LIMITS = dict(max_str_len=1 << 16, max_bin_len=0, max_array_len=1 << 12, max_map_len=1 << 12,
                      max_ext_len=0)
MAX_TREE_DEPTH = 8  # nesting of the config tree carried by `welcome`
MAX_KEY_LEN = 128
MAX_ID = (1 << 31) - 1
MAX_COUNTER = (1 << 63) - 1

# Episode batch limits: generous for real use (32 envs x 40 steps), small enough to bound memory.
MAX_EPISODES = 4096
MAX_STEPS = 10_000  # per episode; the run's own max_steps is checked by unpack_episodes
MAX_FRAMES = 1 << 18  # frames in one batch: 2^18 x 7x7x4 bytes = 49 MiB, under MAX_ARRAY_BYTES
MAX_VIEW = 31
MAX_MISSION_LEN = 64
MAX_TOKEN = 1023

# The largest values any world family sends; the run's own WorldSpec is checked by unpack_episodes.
VIEW_CHANNEL_MAX = tuple(n - 1 for n in world_spec.MAX_CHANNEL_VALUES)
MAX_LATER = world_spec.MAX_LATER
ATTR_MAX = tuple(n - 1 for n in world_spec.MAX_ATTR_VALUES)  # attribute indices; -1 = none
N_ACTIONS = world_spec.MAX_ACTIONS
N_OUTCOMES = world_spec.N_OUTCOMES

Bound = Union[int, float, tuple, None]


@dataclass(frozen=True)
class Field:
    """A header field. `kind` says what values are allowed:

    int, float, bool, str (free text up to max_len), name (identifier-like text), tree (nested plain data:
    the config), strmap (str -> str), numbers (str -> finite number), flat (str -> number, text, bool or nil).
    `sym` ties an int field to an array dimension of the same symbol (e.g. count == number of episodes).
    """

    name: str
    kind: str
    lo: float | None = None
    hi: float | None = None
    max_len: int = 256  # text length, or entries of a map
    required: bool = True
    default: Any = None
    sym: str | None = None


@dataclass(frozen=True)
class Dim:
    """One array dimension: lo <= size <= hi; dimensions sharing `sym` must be equal across arrays."""

    lo: int
    hi: int
    sym: str | None = None


def exact(n: int) -> Dim:
    return Dim(n, n)


@dataclass(frozen=True)
class Array:
    """An array frame. `dims=None` admits any rank up to MAX_NDIM (weights, whose shapes the network decides).

    `lo`/`hi` bound the values: a scalar, or a tuple giving one bound per index of the last axis (the view's
    channels, the attribute columns). Float arrays must be finite unless `allow_nonfinite`.
    """

    name: str
    dtype: str
    dims: tuple[Dim, ...] | None
    lo: Bound = None
    hi: Bound = None
    allow_nonfinite: bool = False
    required: bool = True

    @property
    def wire_dtype(self) -> str:
        """The dtype string that travels in the header: always little-endian, e.g. '<f4', '|u1'."""
        return np.dtype(self.dtype).newbyteorder("<").str


@dataclass(frozen=True)
class MessageSpec:
    type: str
    fields: tuple[Field, ...] = ()
    arrays: tuple[Array, ...] = ()
    # Template for arrays whose names the sender chooses (weights); its `name` is ignored.
    any_arrays: Array | None = None
    # One self-contained frame instead of header + array frames: a CONFLATE subscriber keeps only the last
    # frame it received, so a multipart message would reach it torn.
    one_frame: bool = False

    def array(self, name: str) -> Array | None:
        return next((a for a in self.arrays if a.name == name), None)


# Shared dimensions of an episode batch: N episodes, S steps in all, F = S + N frames, V view side,
# L mission length.
_N = Dim(1, MAX_EPISODES, "N")
_S = Dim(1, MAX_FRAMES, "S")
_F = Dim(2, MAX_FRAMES, "F")
_V = Dim(3, MAX_VIEW, "V")
_L = Dim(1, MAX_MISSION_LEN, "L")

_ROLE = Field("role", "name", max_len=32)
_ID = Field("id", "int", -1, MAX_ID)  # -1: a role that has not been welcomed (given an index) yet

_SPECS: tuple[MessageSpec, ...] = (
    MessageSpec("hello", fields=(
        _ROLE,
        Field("host", "str", max_len=255),
        Field("pid", "int", 0, MAX_ID),
        Field("protocol", "int", 0, 1 << 16),
        # The index a role asks for (an actor's id fixes its epsilon across restarts); -1: assign one.
        Field("index", "int", -1, MAX_ID, required=False, default=-1),
    )),
    MessageSpec("welcome", fields=(
        Field("config", "tree", max_len=1024),
        Field("endpoints", "strmap", max_len=64),
        Field("protocol", "int", 0, 1 << 16),
        Field("index", "int", 0, MAX_ID),  # the role's assigned index, e.g. the actor id
    )),
    MessageSpec("refuse", fields=(
        Field("reason", "str", max_len=2048),
        Field("protocol", "int", 0, 1 << 16, required=False),  # the refuser's version, to explain a mismatch
    )),
    MessageSpec("register", fields=(
        _ROLE,
        Field("endpoint", "str", max_len=255),
    )),
    MessageSpec("episodes", fields=(
        Field("count", "int", 1, MAX_EPISODES, sym="N"),
        # The relabeler's only: originals it kept out of the replay since its last message, counted by the
        # learner as played (relabel.withheld_while_gated; wire/episodes.py checks the sender and the sum).
        Field("withheld_episodes", "int", 0, MAX_COUNTER, required=False, default=0),
        Field("withheld_frames", "int", 0, MAX_COUNTER, required=False, default=0),
    ), arrays=(
        Array("frames", "uint8", (_F, _V, _V, exact(4)), 0, VIEW_CHANNEL_MAX),
        Array("actions", "uint8", (_S,), 0, N_ACTIONS - 1),
        Array("rewards", "float32", (_S,), 0.0, 1.0),
        Array("lengths", "int32", (_N,), 1, MAX_STEPS),
        Array("mission", "int64", (_N, _L), 0, MAX_TOKEN),
        Array("outcome", "uint8", (_N,), 0, N_OUTCOMES - 1),
        Array("picked", "int8", (_N, exact(4)), -1, ATTR_MAX),
        Array("goal", "int8", (_N, exact(4)), -1, ATTR_MAX),
        Array("pick_step", "int32", (_N,), -1, MAX_STEPS - 1),
        Array("later_achieved", "int8", (_N, exact(MAX_LATER), exact(4)), -1, ATTR_MAX),
        Array("later_step", "int32", (_N, exact(MAX_LATER)), -1, MAX_STEPS - 1),
        Array("relabelled", "uint8", (_N,), 0, 1),
        Array("actor_id", "int32", (_N,), 0, MAX_ID),
        Array("weights_version", "int64", (_N,), 0, MAX_COUNTER),
    )),
    MessageSpec("weights", fields=(
        Field("version", "int", 0, MAX_COUNTER),
        # The learner's env frame count when these weights were published: the one clock for the
        # actors' epsilon schedule (the runner reads the same count directly).
        Field("frames", "int", 0, MAX_COUNTER, required=False, default=0),
    ), any_arrays=Array("*", "float32", None), one_frame=True),
    MessageSpec("heartbeat", fields=(
        _ROLE, _ID,
        Field("state", "str", max_len=64),
        Field("counters", "numbers", max_len=256),
    )),
    MessageSpec("stats", fields=(
        _ROLE, _ID,
        Field("values", "flat", max_len=512),
    )),
    # The learner's metrics record for dashboards (names in higher_dist/metrics.py); one frame, because
    # the dashboard's SUB socket is CONFLATEd and keeps only the newest frame.
    MessageSpec("telemetry", fields=(
        Field("record", "tree", max_len=1024),
    ), one_frame=True),
    MessageSpec("stop", fields=(
        Field("reason", "str", max_len=2048, required=False, default=""),
    )),
)

SPECS: dict[str, MessageSpec] = {spec.type: spec for spec in _SPECS}
MESSAGE_TYPES: tuple[str, ...] = tuple(SPECS)


# ------------------------------------------------------------------------------------- checking header fields

_NAME_RE = re.compile(r"[A-Za-z0-9_.:\-]+")
_MAX_FLAT_TEXT = 1024


def check_fields(spec: MessageSpec, fields: dict[str, Any]) -> dict[str, Any]:
    """The fields with defaults filled in, or WireError."""
    known = {f.name for f in spec.fields}
    extra = [name for name in fields if name not in known]
    if extra:
        raise WireError("field", "%s: unexpected fields %s" % (spec.type, [str(x)[:32] for x in extra[:5]]))
    out = {}
    for f in spec.fields:
        if f.name not in fields:
            if f.required:
                raise WireError("field", "%s: missing field %s" % (spec.type, f.name))
            out[f.name] = f.default
            continue
        out[f.name] = _check_value(spec.type, f, fields[f.name])
    return out


def _check_value(msg_type: str, f: Field, value: Any) -> Any:
    where = "%s.%s" % (msg_type, f.name)
    kind = f.kind
    if kind in ("int", "float"):
        number = _number(value, where, integer=kind == "int")
        if (f.lo is not None and number < f.lo) or (f.hi is not None and number > f.hi):
            raise WireError("range", "%s=%r outside [%s, %s]" % (where, number, f.lo, f.hi))
        return number
    if kind == "bool":
        if not isinstance(value, bool):
            raise WireError("field", "%s: expected true or false" % where)
        return value
    if kind in ("str", "name"):
        return _text(value, where, f.max_len, identifier=kind == "name")
    if kind == "tree":
        _tree(value, where, 0, f.max_len)
        if not isinstance(value, dict):
            raise WireError("field", "%s: expected a map" % where)
        return value
    if kind in ("strmap", "numbers", "flat"):
        if not isinstance(value, dict) or len(value) > f.max_len:
            raise WireError("field", "%s: expected a map of at most %d entries" % (where, f.max_len))
        for key, item in value.items():
            _text(key, where, MAX_KEY_LEN)
            if kind == "strmap":
                _text(item, "%s[%s]" % (where, key), 1024)
            elif kind == "numbers":
                _number(item, "%s[%s]" % (where, key), integer=False)
            elif not (item is None or isinstance(item, bool)):
                if isinstance(item, str):
                    _text(item, "%s[%s]" % (where, key), _MAX_FLAT_TEXT)
                else:
                    _number(item, "%s[%s]" % (where, key), integer=False)
        return value
    raise AssertionError("schema declares an unknown field kind %r" % kind)  # a bug in schema.py


def _number(value: Any, where: str, integer: bool) -> int | float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        raise WireError("field", "%s: expected %s" % (where, "an integer" if integer else "a number"))
    if isinstance(value, float) and not math.isfinite(value):
        raise WireError("nan", "%s is not finite" % where)
    return value


def _text(value: Any, where: str, max_len: int, identifier: bool = False) -> str:
    if not isinstance(value, str) or len(value) > max_len:
        raise WireError("field", "%s: expected text of at most %d characters" % (where, max_len))
    if identifier and not _NAME_RE.fullmatch(value):
        raise WireError("field", "%s: expected a name of letters, digits and _.:-" % where)
    return value


def _tree(value: Any, where: str, depth: int, max_len: int) -> None:
    """Plain nested data (the config): maps with text keys, lists, text, finite numbers, bools, nil."""
    if depth > MAX_TREE_DEPTH:
        raise WireError("field", "%s: nested deeper than %d" % (where, MAX_TREE_DEPTH))
    if value is None or isinstance(value, (bool, int)):
        return
    if isinstance(value, float):
        if not math.isfinite(value):
            raise WireError("nan", "%s is not finite" % where)
        return
    if isinstance(value, str):
        _text(value, where, 4096)
        return
    if isinstance(value, (list, dict)) and len(value) > max_len:
        raise WireError("field", "%s: more than %d entries" % (where, max_len))
    if isinstance(value, list):
        for item in value:
            _tree(item, where, depth + 1, max_len)
        return
    if isinstance(value, dict):
        for key, item in value.items():
            _text(key, where, MAX_KEY_LEN)
            _tree(item, "%s.%s" % (where, key), depth + 1, max_len)
        return
    raise WireError("field", "%s: unsupported value of type %s" % (where, type(value).__name__))
