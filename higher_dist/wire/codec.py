"""Encode and decode wire messages: a msgpack header frame followed by one raw frame per array.

Header (a msgpack map with exactly these keys):
    type    message type (schema.SPECS)
    v       schema/protocol version (schema.PROTOCOL_VERSION)
    sender  free short text naming the sender, e.g. "actor-3"
    seq     sender's sequence number
    fields  the type's header fields
    arrays  [[name, dtype, shape, nbytes], ...] in frame order

One-frame types (weights) pack the same header and the array bytes into a single frame:
    MAGIC (4 bytes) | header length (uint32 little-endian) | header | pad | array 0 | pad | array 1 ...
where each array starts at the next multiple of 8 bytes from the frame start (offsets are recomputed by the
receiver from the declared byte lengths, so there is nothing extra to trust).

`decode` trusts nothing: every problem raises `WireError` with a short `reason` code (see REASONS), and it
checks sizes before it allocates, so a lying header costs nothing. Arrays are zero-copy, read-only views
of the received frames.
"""
from __future__ import annotations

import functools
import math
import struct
import sys
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import msgpack
import numpy as np

from higher_dist.wire import schema as S
from higher_dist.wire.schema import REASONS, WireError, check_fields  # noqa: F401 (REASONS re-exported)

MAGIC = b"HDW\x01"
_PREFIX = struct.Struct("<4sI")
_ALIGN = 8
_HEADER_KEYS = frozenset(("type", "v", "sender", "seq", "fields", "arrays"))
_MAX_SENDER = 64


@dataclass
class Message:
    type: str
    version: int
    sender: str
    seq: int
    fields: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------- encode

def encode(msg_type: str, fields: Mapping[str, Any] | None = None, arrays: Mapping[str, np.ndarray] | None = None,
           sender: str = "", seq: int = 0) -> list[bytes | memoryview]:
    """Frames for `send_multipart`: [header, array bytes...] (or [one frame] for one-frame types).

    The header is checked against the schema here too, so a sender's bug fails loudly at the sender instead
    of as silent drops at the receiver. Array values are not scanned (the receiver does it). Array frames
    are memoryviews of the arrays (zero-copy): do not modify an array until it has been sent.
    """
    spec = S.SPECS.get(msg_type)
    if spec is None:
        raise WireError("unknown_type", repr(msg_type))
    plain_fields = {name: _plain(value) for name, value in (fields or {}).items()}
    checked = check_fields(spec, plain_fields)
    arrays = arrays or {}
    wire_arrays = [(name, _little_endian(_contiguous(arr))) for name, arr in arrays.items()]
    descriptors = [[name, arr.dtype.str, list(arr.shape), arr.nbytes] for name, arr in wire_arrays]
    _check_descriptors(spec, descriptors, checked)
    header = msgpack.packb({"type": msg_type, "v": S.PROTOCOL_VERSION, "sender": _check_sender(sender),
                            "seq": _check_seq(seq), "fields": plain_fields, "arrays": descriptors},
                           use_bin_type=True)
    if spec.one_frame:
        return [_one_frame(header, [arr for _, arr in wire_arrays])]
    return [header] + [_byte_view(arr) for _, arr in wire_arrays]


def encode_weights(version: int, arrays: Mapping[str, np.ndarray], sender: str = "", seq: int = 0,
                   frames: int = 0) -> bytes:
    """One frame carrying a weights version, the learner's frame count and named float32 arrays (for a
    CONFLATE subscriber)."""
    as_float = {name: np.asarray(arr, dtype=np.float32) for name, arr in arrays.items()}
    return encode("weights", {"version": version, "frames": int(frames)}, as_float, sender, seq)[0]


def _contiguous(arr: Any) -> np.ndarray:
    # Not np.ascontiguousarray: it turns 0-d arrays into shape (1,).
    arr = np.asarray(arr)
    return arr if arr.flags.c_contiguous else arr.copy(order="C")


def _little_endian(arr: np.ndarray) -> np.ndarray:
    order = arr.dtype.byteorder
    if order == ">" or (order == "=" and sys.byteorder == "big"):
        return arr.astype(arr.dtype.newbyteorder("<"))
    return arr


def _byte_view(arr: np.ndarray) -> memoryview:
    return memoryview(arr.reshape(-1).view(np.uint8))


def _one_frame(header: bytes, arrays: list[np.ndarray]) -> bytes:
    offsets, _ = _layout(_PREFIX.size + len(header), [arr.nbytes for arr in arrays])
    parts: list[bytes | memoryview] = [_PREFIX.pack(MAGIC, len(header)), header]
    position = _PREFIX.size + len(header)
    for offset, arr in zip(offsets, arrays):
        parts.append(bytes(offset - position))  # alignment padding
        parts.append(_byte_view(arr))
        position = offset + arr.nbytes
    return b"".join(parts)  # one copy of the payload, straight into the frame


def _layout(start: int, sizes: Sequence[int]) -> tuple[list[int], int]:
    """Offsets of arrays placed after `start`, each aligned to 8 bytes, and the total length."""
    offsets, position = [], start
    for size in sizes:
        position = -(-position // _ALIGN) * _ALIGN
        offsets.append(position)
        position += size
    return offsets, position


def _plain(value: Any, depth: int = 0) -> Any:
    """numpy scalars and tuples as msgpack-native values (Config.to_dict has tuples, counters numpy ints)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)) and depth < S.MAX_TREE_DEPTH:
        return [_plain(item, depth + 1) for item in value]
    if isinstance(value, dict) and depth < S.MAX_TREE_DEPTH:
        return {key: _plain(item, depth + 1) for key, item in value.items()}
    return value


# ----------------------------------------------------------------------------------------------------- decode

def decode(frames: Sequence[Any]) -> Message:
    """Validate and decode received frames (bytes, memoryviews or zmq.Frame). Raises WireError only."""
    if not isinstance(frames, (list, tuple)) or not 1 <= len(frames) <= 1 + S.MAX_ARRAYS:
        raise WireError("frame_count", "expected 1 to %d frames" % (1 + S.MAX_ARRAYS))
    buffers = [_as_buffer(frame) for frame in frames]
    first = buffers[0]
    one_frame = len(buffers) == 1 and len(first) >= _PREFIX.size and bytes(first[:4]) == MAGIC
    if one_frame:
        _, header_len = _PREFIX.unpack(first[:_PREFIX.size])
        if header_len > S.MAX_HEADER_BYTES or _PREFIX.size + header_len > len(first):
            raise WireError("size", "one-frame header length %d does not fit" % header_len)
        header_bytes = first[_PREFIX.size:_PREFIX.size + header_len]
    else:
        if len(first) > S.MAX_HEADER_BYTES:
            raise WireError("size", "header of %d bytes" % len(first))
        header_bytes = first
    header = _unpack_header(header_bytes)
    spec = S.SPECS[header["type"]]
    fields = check_fields(spec, header["fields"])
    descriptors = _check_descriptors(spec, header["arrays"], fields)
    if spec.one_frame != one_frame:
        raise WireError("frame_count", "%s must be sent as %s" % (spec.type, "one frame" if spec.one_frame
                                                                       else "header + array frames"))
    if one_frame:
        offsets, total = _layout(_PREFIX.size + len(header_bytes), [d[3] for d in descriptors])
        if total != len(first):
            raise WireError("size", "frame of %d bytes, header declares %d" % (len(first), total))
        payloads = [first[o:o + d[3]] for o, d in zip(offsets, descriptors)]
    else:
        if len(buffers) != 1 + len(descriptors):
            raise WireError("frame_count", "%d array frames for %d arrays" % (len(buffers) - 1, len(descriptors)))
        payloads = buffers[1:]
    arrays = {}
    for (name, dtype, shape, nbytes), payload in zip(descriptors, payloads):
        if len(payload) != nbytes:
            raise WireError("size", "array %s: frame of %d bytes, declared %d" % (name, len(payload), nbytes))
        arr = np.frombuffer(payload, dtype=dtype).reshape(shape)
        arr.flags.writeable = False  # a view of a received frame: never written through
        _check_values(spec.array(name) or spec.any_arrays, name, arr)
        arrays[name] = arr
    return Message(header["type"], header["v"], header["sender"], header["seq"], fields, arrays)


def decode_weights(frame: Any, expected: Mapping[str, Sequence[int]] | None = None
                   ) -> tuple[int, dict[str, np.ndarray]]:
    """(version, arrays) from one weights frame; with `expected`, names and shapes must match exactly.

    The arrays are writable copies (a network loads them anyway, and torch warns on read-only buffers).
    """
    return weights_of(decode([frame]), expected)


def weights_of(msg: Message, expected: Mapping[str, Sequence[int]] | None = None
               ) -> tuple[int, dict[str, np.ndarray]]:
    """(version, writable copies of the arrays) of a decoded weights message; WireError otherwise."""
    if msg.type != "weights":
        raise WireError("unknown_type", "expected weights, got %s" % msg.type)
    check_weight_shapes(msg.arrays, expected)
    return msg.fields["version"], {name: arr.copy() for name, arr in msg.arrays.items()}


def check_weight_shapes(arrays: Mapping[str, np.ndarray], expected: Mapping[str, Sequence[int]] | None) -> None:
    if expected is None:
        return
    if set(arrays) != set(expected):
        missing, extra = sorted(set(expected) - set(arrays)), sorted(set(arrays) - set(expected))
        raise WireError("field", "weights names differ: missing %s, unexpected %s" % (missing[:5], extra[:5]))
    for name, arr in arrays.items():
        if tuple(arr.shape) != tuple(expected[name]):
            raise WireError("shape", "weights %s: shape %s, expected %s" % (name, arr.shape, tuple(expected[name])))


def _as_buffer(frame: Any) -> memoryview:
    buffer = getattr(frame, "buffer", None)  # zmq.Frame exposes its bytes as .buffer
    if buffer is not None and not isinstance(frame, (bytes, bytearray, memoryview)):
        frame = buffer
    if not isinstance(frame, (bytes, bytearray, memoryview)):
        raise WireError("bad_frames", "frame of type %s" % type(frame).__name__)
    view = memoryview(frame)
    if view.ndim != 1 or view.itemsize != 1:
        try:
            view = view.cast("B")
        except (TypeError, ValueError) as exc:
            raise WireError("bad_frames", "frame is not a flat byte buffer") from exc
    return view


def _unpack_header(data: memoryview) -> dict[str, Any]:
    try:
        header = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True, **S.MSGPACK_LIMITS)
    except Exception as exc:  # msgpack raises ValueError subclasses, and others on odd input: all mean "not ours"
        raise WireError("bad_msgpack", type(exc).__name__) from exc
    if not isinstance(header, dict):
        raise WireError("header", "not a map")
    # The version first: a peer of another version may well have other header keys, and "version" is the
    # reason an operator needs to see.
    version = header.get("v")
    if type(version) is not int:
        raise WireError("header", "version is missing or not an integer")
    if version != S.PROTOCOL_VERSION:
        raise WireError("version", "peer speaks version %d, we speak %d" % (version, S.PROTOCOL_VERSION),
                        peer_version=version)
    if set(header) != _HEADER_KEYS:
        raise WireError("header", "keys %s" % sorted(map(str, header))[:8])
    if not isinstance(header["type"], str) or header["type"] not in S.SPECS:
        raise WireError("unknown_type", repr(header["type"])[:40])
    _check_sender(header["sender"], "header")
    _check_seq(header["seq"], "header")
    if not isinstance(header["fields"], dict) or not isinstance(header["arrays"], list):
        raise WireError("header", "fields must be a map and arrays a list")
    return header


def _check_sender(sender: Any, reason: str = "field") -> str:
    if not isinstance(sender, str) or len(sender) > _MAX_SENDER:
        raise WireError(reason, "sender must be text of at most %d characters" % _MAX_SENDER)
    return sender


def _check_seq(seq: Any, reason: str = "field") -> int:
    if type(seq) is not int or not 0 <= seq <= S.MAX_COUNTER:
        raise WireError(reason, "seq must be an integer in [0, 2^63)")
    return seq


# ------------------------------------------------------------------------------------------------------ arrays

def _check_descriptors(spec: S.MessageSpec, descriptors: Any, fields: dict[str, Any]) -> list[tuple]:
    """Validated [(name, dtype, shape, nbytes)], checked against the schema before anything is allocated."""
    if len(descriptors) > S.MAX_ARRAYS:
        raise WireError("size", "%d arrays" % len(descriptors))
    out, seen, symbols, total = [], set(), {}, 0
    for desc in descriptors:
        if not isinstance(desc, list) or len(desc) != 4:
            raise WireError("header", "array descriptor must be [name, dtype, shape, nbytes]")
        name, dtype, shape, nbytes = desc
        if not isinstance(name, str) or not name or len(name) > S.MAX_KEY_LEN or name in seen:
            raise WireError("field", "bad or repeated array name %r" % str(name)[:40])
        seen.add(name)
        aspec = spec.array(name) or spec.any_arrays
        if aspec is None:
            raise WireError("field", "%s: unexpected array %s" % (spec.type, name))
        if dtype != aspec.wire_dtype:
            raise WireError("dtype", "%s.%s: dtype %r, expected %s" % (spec.type, name, str(dtype)[:16],
                                                                     aspec.wire_dtype))
        if type(nbytes) is not int or not 0 <= nbytes <= S.MAX_ARRAY_BYTES:
            raise WireError("size", "%s.%s: declared %r bytes" % (spec.type, name, nbytes))
        total += nbytes
        if total > S.MAX_PAYLOAD_BYTES:
            raise WireError("size", "%s: arrays exceed %d bytes" % (spec.type, S.MAX_PAYLOAD_BYTES))
        shape = _check_shape(spec, aspec, name, shape, symbols)
        if math.prod(shape) * np.dtype(dtype).itemsize != nbytes:
            raise WireError("shape", "%s.%s: shape %s does not make %d bytes" % (spec.type, name, shape, nbytes))
        out.append((name, dtype, shape, nbytes))
    missing = [a.name for a in spec.arrays if a.required and a.name not in seen]
    if missing:
        raise WireError("field", "%s: missing arrays %s" % (spec.type, missing))
    for f in spec.fields:
        if f.sym is not None and f.sym in symbols and fields.get(f.name) != symbols[f.sym]:
            raise WireError("shape", "%s.%s=%r but arrays have %d" % (spec.type, f.name, fields.get(f.name),
                                                                   symbols[f.sym]))
    return out


def _check_shape(spec: S.MessageSpec, aspec: S.Array, name: str, shape: Any, symbols: dict[str, int]) -> tuple:
    where = "%s.%s" % (spec.type, name)
    if not isinstance(shape, list) or len(shape) > S.MAX_NDIM:
        raise WireError("shape", "%s: shape must be a list of at most %d dims" % (where, S.MAX_NDIM))
    if any(type(n) is not int or not 0 <= n <= S.MAX_DIM for n in shape):
        raise WireError("shape", "%s: dims must be integers in [0, %d]" % (where, S.MAX_DIM))
    if aspec.dims is None:
        return tuple(shape)
    if len(shape) != len(aspec.dims):
        raise WireError("shape", "%s: rank %d, expected %d" % (where, len(shape), len(aspec.dims)))
    for axis, (n, dim) in enumerate(zip(shape, aspec.dims)):
        if not dim.lo <= n <= dim.hi:
            raise WireError("shape", "%s: dim %d is %d, allowed [%d, %d]" % (where, axis, n, dim.lo, dim.hi))
        if dim.sym is not None:
            if symbols.setdefault(dim.sym, n) != n:
                raise WireError("shape", "%s: dim %d is %d, other arrays say %s=%d" % (where, axis, n, dim.sym,
                                                                                      symbols[dim.sym]))
    return tuple(shape)


def _check_values(aspec: S.Array, name: str, arr: np.ndarray) -> None:
    if arr.size == 0:
        return
    if arr.dtype.kind == "f" and not aspec.allow_nonfinite and not np.isfinite(arr).all():
        raise WireError("nan", "%s has NaN or infinite values" % name)
    lo, hi = aspec.lo, aspec.hi
    if not isinstance(lo, tuple) and not isinstance(hi, tuple):
        _check_bounds(arr, lo, hi, name)
        return
    # Per-index bounds along the last axis (view channels, attribute columns). One strided scan per column
    # is ~30x faster here than numpy's axis-0 min/max over a 4-wide array.
    columns = arr.reshape(-1, arr.shape[-1])
    for i in range(columns.shape[1]):
        _check_bounds(columns[:, i], lo[i] if isinstance(lo, tuple) else lo, hi[i] if isinstance(hi, tuple) else hi,
                      "%s[..., %d]" % (name, i))


def _check_bounds(arr: np.ndarray, lo: float | None, hi: float | None, name: str) -> None:
    # A bound the dtype cannot violate (uint8 >= 0) costs nothing.
    dtype_min, dtype_max = _dtype_limits(arr.dtype)
    if lo is not None and lo > dtype_min and arr.min() < lo:
        raise WireError("range", "%s below %s" % (name, lo))
    if hi is not None and hi < dtype_max and arr.max() > hi:
        raise WireError("range", "%s above %s" % (name, hi))


@functools.lru_cache(maxsize=None)
def _dtype_limits(dtype: np.dtype) -> tuple[float, float]:
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        return info.min, info.max
    return -math.inf, math.inf
