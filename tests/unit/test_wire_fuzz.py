"""Fuzz the decoder: whatever arrives, `decode` returns a Message or raises WireError, and nothing else escapes.

Each test starts from valid messages and breaks them in one way (random bytes, random headers, mutated header
entries, dropped or added frames, flipped bytes, injected values), so that the inputs reach deep into the
validation instead of failing at the first msgpack byte.
"""
from __future__ import annotations

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dataclasses import replace

from higher_dist.config import WorldConfig
from higher_dist.learning.episode import Episode
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.world.spec import MAX_ACTIONS, MAX_ATTR_VALUES, MAX_CHANNEL_VALUES, WorldSpec
from higher_dist.wire import (MESSAGE_TYPES, PROTOCOL_VERSION, Message, WireError, decode, encode, encode_weights,
                              pack_episodes, unpack_episodes)
from higher_dist.wire.schema import MAX_STEPS as MAX_SCHEMA_STEPS
from higher_dist.wire.schema import MAX_TOKEN, SPECS

SPEC = WorldSpec.of(WorldConfig())
VOCAB = SPEC.vocab_size
MAX_STEPS = SPEC.max_steps
POOL = real_episodes(WorldConfig(), 60, seed=0, relabelled=True)
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _episode(rng: np.random.Generator, length: int | None = None) -> Episode:
    """A real episode from the pool, of the given length where the pool has one."""
    fits = [ep for ep in POOL if length is None or ep.length == length] or POOL
    return replace(fits[int(rng.integers(len(fits)))], actor_id=1, weights_version=2)


def _valid_messages() -> dict[str, list[bytes]]:
    rng = np.random.default_rng(0)
    episodes = [_episode(rng, int(rng.integers(1, MAX_STEPS + 1))) for _ in range(3)]
    out = {
        "hello": encode("hello", {"role": "actor", "host": "h", "pid": 1, "protocol": 1}),
        "welcome": encode("welcome", {"config": {"a": {"b": [1, 2.5, "x", None, True]}},
                                      "endpoints": {"weights": "tcp://h:1"}, "protocol": 1, "index": 0}),
        "refuse": encode("refuse", {"reason": "no"}),
        "register": encode("register", {"role": "relabeler", "endpoint": "tcp://h:2"}),
        "episodes": encode("episodes", *pack_episodes(episodes)),
        "weights": [encode_weights(3, {"w": rng.standard_normal((4, 3)), "b": np.zeros(3)})],
        "heartbeat": encode("heartbeat", {"role": "actor", "id": 0, "state": "run", "counters": {"f": 1}}),
        "stats": encode("stats", {"role": "learner", "id": 0, "values": {"loss": 0.5, "p": "x"}}),
        "telemetry": encode("telemetry", {"record": {"frames": 10, "roles": [{"role": "actor", "pid": 3}],
                                                   "loss": None}}),
        "stop": encode("stop"),
    }
    assert set(out) == set(MESSAGE_TYPES)
    return {name: [bytes(f) for f in frames] for name, frames in out.items()}


VALID = _valid_messages()
message_names = st.sampled_from(sorted(VALID))

# Anything msgpack can carry, nested: the raw material of hostile headers.
msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2 ** 63), 2 ** 64 - 1) | st.floats() | st.text(max_size=20)
    | st.binary(max_size=20),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=8), children, max_size=5),
    max_leaves=20,
)


def _decode_or_wire_error(frames) -> Message | None:
    """The property under test: a Message, or WireError with a known reason; any other exception fails."""
    try:
        msg = decode(frames)
    except WireError as exc:
        assert exc.reason
        return None
    assert isinstance(msg, Message)
    return msg


@FUZZ
@given(st.lists(st.binary(max_size=200), min_size=0, max_size=14))
def test_random_frames(frames):
    _decode_or_wire_error(frames)


@FUZZ
@given(msgpack_values, st.lists(st.binary(max_size=64), max_size=3))
def test_random_msgpack_headers(header, extra_frames):
    packed = msgpack.packb(header, use_bin_type=True)
    assert _decode_or_wire_error([packed, *extra_frames]) is None


@FUZZ
@given(message_names, st.sampled_from(["type", "v", "sender", "seq", "fields", "arrays", "other"]),
       msgpack_values, st.booleans())
def test_mutated_header_entries(name, key, value, delete):
    frames = VALID[name]
    if SPECS[name].one_frame:
        return  # one-frame form: covered by test_flipped_bytes_weights
    header = msgpack.unpackb(frames[0])
    if delete:
        header.pop(key, None)
    else:
        header[key] = value
    _decode_or_wire_error([msgpack.packb(header, use_bin_type=True), *frames[1:]])


@FUZZ
@given(message_names, st.data())
def test_mutated_fields_and_descriptors(name, data):
    frames = VALID[name]
    if SPECS[name].one_frame:
        return
    header = msgpack.unpackb(frames[0])
    if header["fields"] and data.draw(st.booleans()):
        field = data.draw(st.sampled_from(sorted(header["fields"])))
        header["fields"][field] = data.draw(msgpack_values)
    elif header["arrays"]:
        desc = data.draw(st.sampled_from(header["arrays"]))
        position = data.draw(st.integers(0, 3))
        desc[position] = data.draw(msgpack_values | st.integers(0, 2 ** 62) | st.lists(st.integers(0, 2 ** 40),
                                                                                        max_size=7))
    _decode_or_wire_error([msgpack.packb(header, use_bin_type=True), *frames[1:]])


@FUZZ
@given(message_names, st.integers(0, 20), st.lists(st.binary(max_size=16), max_size=3))
def test_truncated_and_extra_frames(name, keep, extra):
    frames = VALID[name]
    cut = frames[:min(keep, len(frames))]
    broken = cut + extra
    if broken == frames:
        return
    assert _decode_or_wire_error(broken) is None


@FUZZ
@given(st.integers(-(2 ** 63), 2 ** 63 - 1).filter(lambda v: v != PROTOCOL_VERSION), message_names)
def test_wrong_version(version, name):
    frames = VALID[name]
    if SPECS[name].one_frame:
        return
    header = msgpack.unpackb(frames[0])
    header["v"] = version
    try:
        decode([msgpack.packb(header), *frames[1:]])
    except WireError as exc:
        assert exc.reason == "version"
    else:
        raise AssertionError("a wrong version was accepted")


@FUZZ
@given(st.data())
def test_flipped_bytes_episodes(data):
    frames = [bytearray(f) for f in VALID["episodes"]]
    for _ in range(data.draw(st.integers(1, 4))):
        index = data.draw(st.integers(0, len(frames) - 1))
        if not frames[index]:
            continue
        position = data.draw(st.integers(0, len(frames[index]) - 1))
        frames[index][position] = data.draw(st.integers(0, 255))
    msg = _decode_or_wire_error([bytes(f) for f in frames])
    if msg is not None:
        try:
            episodes = unpack_episodes(msg, SPEC)
        except WireError:
            return
        assert all(0 <= ep.actions.min() and ep.actions.max() < 4 for ep in episodes)
        assert all(np.isfinite(ep.rewards).all() for ep in episodes)


@FUZZ
@given(st.data())
def test_flipped_bytes_weights(data):
    frame = bytearray(VALID["weights"][0])
    position = data.draw(st.integers(0, len(frame) - 1))
    frame[position] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(frame)))
    _decode_or_wire_error([bytes(frame[:cut]) if data.draw(st.booleans()) else bytes(frame)])


@FUZZ
@given(st.sampled_from(["actions", "rewards", "mission", "frames", "outcome", "picked", "goal", "later_achieved",
                        "later_step", "relabelled"]),
       st.data())
def test_injected_bad_values_are_rejected(array_name, data):
    rng = np.random.default_rng(data.draw(st.integers(0, 1000)))
    fields, arrays = pack_episodes([_episode(rng, int(rng.integers(1, MAX_STEPS + 1))) for _ in range(3)])
    arr = arrays[array_name].copy()
    flat = arr.reshape(-1)
    position = data.draw(st.integers(0, flat.size - 1))
    if array_name == "rewards":
        flat[position] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf, -0.5, 1.5, 1e30]))
    elif array_name == "mission":
        flat[position] = data.draw(st.integers(VOCAB, 2 ** 62))
    elif array_name == "frames":
        channel = position % 4
        flat[position] = data.draw(st.integers((4, 6, 5, 5)[channel] + 1, 255))
    elif array_name in ("picked", "goal", "later_achieved"):
        flat[position] = data.draw(st.integers(-128, -2) | st.integers(6, 127))
    elif array_name == "later_step":
        flat[position] = data.draw(st.integers(-2 ** 31, -2) | st.integers(MAX_SCHEMA_STEPS, 2 ** 31 - 1))
    else:
        high = {"actions": 3, "outcome": 2, "relabelled": 1}[array_name]
        flat[position] = data.draw(st.integers(high + 1, 255))
    arrays[array_name] = arr
    frames = encode("episodes", fields, arrays)
    try:
        unpack_episodes(decode(frames), SPEC)
    except WireError as exc:
        expected = "nan" if array_name == "rewards" and not np.isfinite(flat[position]) else "range"
        if array_name == "mission" and flat[position] <= MAX_TOKEN:
            expected = "mission_token"  # under the schema's cap: the run's vocabulary refuses it
        if array_name == "actions" and flat[position] < MAX_ACTIONS:
            expected = "action"  # another world's action (BabyAI has 7): the run's spec refuses it
        if array_name == "frames" and flat[position] < MAX_CHANNEL_VALUES[position % 4]:
            expected = "cell"  # another world's cell (BabyAI's objects): the run's spec refuses it
        if array_name in ("picked", "goal", "later_achieved") and 0 <= flat[position] < MAX_ATTR_VALUES[position % 4]:
            expected = "attribute"  # another world's value (a BabyAI location mask): the run's spec refuses it
        assert exc.reason == expected
    else:
        raise AssertionError(f"an out-of-range {array_name} value was accepted")


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, MAX_STEPS), min_size=1, max_size=12), st.integers(0, 2 ** 32 - 1))
def test_any_valid_batch_round_trips(lengths, seed):
    rng = np.random.default_rng(seed)
    episodes = [_episode(rng, length) for length in lengths]
    back = unpack_episodes(decode(encode("episodes", *pack_episodes(episodes))), SPEC)
    assert [ep.length for ep in back] == [ep.length for ep in episodes]
    for a, b in zip(episodes, back):
        assert np.array_equal(a.frames, b.frames) and np.array_equal(a.rewards, b.rewards)
        assert np.array_equal(a.mission, b.mission) and a.outcome == b.outcome
