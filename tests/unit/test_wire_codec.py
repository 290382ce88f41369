"""Codec round trips for every message type, episode batches, and targeted rejections by reason."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from dataclasses import replace

from higher_dist.config import WorldConfig, from_dict
from higher_dist.config_presets import make_config
from higher_dist.learning.episode import Episode
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import (MESSAGE_TYPES, PROTOCOL_VERSION, SPECS, WireError, decode, decode_weights, encode,
                              encode_weights, pack_episodes, unpack_episodes)
from higher_dist.wire.codec import MAGIC
from higher_dist.world.spec import MAX_ACTIONS, MAX_ATTR_VALUES, MAX_CHANNEL_VALUES, WorldSpec

SPEC = WorldSpec.of(WorldConfig())
MAX_STEPS = SPEC.max_steps


def episode_batch(n: int = 5, seed: int = 0) -> list[Episode]:
    """Real episodes of every outcome, relabelled copies included, with varied ids and versions."""
    episodes = real_episodes(WorldConfig(), n, seed=seed, relabelled=True)
    return [replace(ep, actor_id=i % 3, weights_version=7 * i) for i, ep in enumerate(episodes)]


def sample_message(msg_type: str) -> tuple[dict, dict]:
    """Valid (fields, arrays) for each type; the round-trip test fails if a new type has none."""
    cfg = make_config("higher", "small")
    return {
        "hello": ({"role": "actor", "host": "node-1.example", "pid": 4242, "protocol": PROTOCOL_VERSION,
                   "index": 2}, {}),
        "welcome": ({"config": cfg.to_dict(), "endpoints": {"experience": "tcp://10.0.0.1:5556",
                                                           "weights": "tcp://10.0.0.1:5557"},
                     "protocol": PROTOCOL_VERSION, "index": 3}, {}),
        "refuse": ({"reason": "protocol 2 is not 1", "protocol": 1}, {}),
        "register": ({"role": "relabeler", "endpoint": "tcp://10.0.0.2:6000"}, {}),
        "episodes": pack_episodes(episode_batch()),
        "weights": ({"version": 17}, {"enc.conv.0.weight": np.random.default_rng(1).standard_normal(
            (32, 16, 3, 3)).astype(np.float32), "head.bias": np.arange(4, dtype=np.float32),
            "scalar": np.array(0.5, np.float32)}),
        "heartbeat": ({"role": "actor", "id": 1, "state": "running",
                       "counters": {"frames": 123456, "episodes": 77, "fps": 1520.5}}, {}),
        "stats": ({"role": "learner", "id": 0, "values": {"loss": 0.031, "updates": 10, "phase": "learn",
                                                          "gate_open": True, "eval": None}}, {}),
        "telemetry": ({"record": {"frames": 1200, "success_rate_eval_train": 0.25, "relabel_gate_open": False,
                                  "roles": [{"role": "actor", "id": 0, "state": "alive", "frames_per_s": None}]}}, {}),
        "stop": ({"reason": "ctrl-c"}, {}),
    }[msg_type]


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES)
def test_round_trip_every_type(msg_type):
    fields, arrays = sample_message(msg_type)
    frames = encode(msg_type, fields, arrays, sender="actor-1", seq=99)
    assert len(frames) == (1 if SPECS[msg_type].one_frame else 1 + len(arrays))
    msg = decode([bytes(f) for f in frames])
    assert (msg.type, msg.version, msg.sender, msg.seq) == (msg_type, PROTOCOL_VERSION, "actor-1", 99)
    expected_fields = {f.name: f.default for f in SPECS[msg_type].fields}
    expected_fields.update(msgpack.unpackb(msgpack.packb(fields)))  # tuples travel as lists
    assert msg.fields == expected_fields
    assert list(msg.arrays) == list(arrays)
    for name, arr in arrays.items():
        assert msg.arrays[name].dtype == arr.dtype and np.array_equal(msg.arrays[name], arr)


def test_welcome_config_rebuilds_the_same_config():
    cfg = make_config("her", "small", seed=7)
    msg = decode(encode("welcome", {"config": cfg.to_dict(), "endpoints": {}, "protocol": 1, "index": 0}))
    assert from_dict(msg.fields["config"]) == cfg


def test_optional_field_gets_its_default():
    assert decode(encode("stop")).fields == {"reason": ""}


def test_episode_batch_round_trip():
    episodes = episode_batch(12, seed=3)
    msg = decode(encode("episodes", *pack_episodes(episodes)))
    back = unpack_episodes(msg, SPEC)
    assert len(back) == len(episodes)
    for a, b in zip(episodes, back):
        for name in ("frames", "actions", "rewards", "mission", "picked", "goal"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y), name
            assert y.flags.writeable
        assert (a.outcome, a.relabelled, a.actor_id, a.weights_version) == \
               (b.outcome, b.relabelled, b.actor_id, b.weights_version)


def test_pack_refuses_empty_and_inconsistent_batches():
    with pytest.raises(ValueError):
        pack_episodes([])
    ep = episode_batch(1)[0]
    ep.frames = ep.frames[:-1]
    with pytest.raises(ValueError):
        pack_episodes([ep])


def test_weights_one_frame_round_trip_and_expected_shapes():
    arrays = sample_message("weights")[1]
    frame = encode_weights(5, arrays)
    assert isinstance(frame, bytes) and frame.startswith(MAGIC)
    version, got = decode_weights(frame, {k: v.shape for k, v in arrays.items()})
    assert version == 5 and all(np.array_equal(got[k], arrays[k]) for k in arrays)
    assert all(arr.flags.writeable for arr in got.values())
    with pytest.raises(WireError) as err:
        decode_weights(frame, {"head.bias": (4,)})
    assert err.value.reason == "field"
    with pytest.raises(WireError) as err:
        decode_weights(frame, {**{k: v.shape for k, v in arrays.items()}, "head.bias": (5,)})
    assert err.value.reason == "shape"


# ---------------------------------------------------------------------------------------------- rejections

def _header(frames):
    return msgpack.unpackb(frames[0])


def _with_header(frames, header):
    return [msgpack.packb(header)] + list(frames[1:])


def _base_batch():
    return pack_episodes(episode_batch(4, seed=1))


def _episodes_frames(**replace_arrays):
    fields, arrays = _base_batch()
    arrays.update(replace_arrays)
    return [bytes(f) for f in encode("episodes", fields, arrays)]


def _reason(frames) -> str:
    with pytest.raises(WireError) as err:
        decode(frames)
    return err.value.reason


def test_rejects_non_msgpack_and_non_map_headers():
    assert _reason([b"\xc1garbage"]) == "bad_msgpack"
    assert _reason([msgpack.packb([1, 2, 3])]) == "header"
    assert _reason([]) == "frame_count"
    assert _reason("not a list") == "frame_count"
    assert _reason([12345]) == "bad_frames"


def test_rejects_wrong_version_and_unknown_type():
    frames = [bytes(f) for f in encode("stop")]
    assert _reason(_with_header(frames, {**_header(frames), "v": PROTOCOL_VERSION + 1})) == "version"
    assert _reason(_with_header(frames, {**_header(frames), "type": "teleport"})) == "unknown_type"


def test_rejects_missing_extra_and_ill_typed_fields():
    frames = [bytes(f) for f in encode("hello", *sample_message("hello"))]
    header = _header(frames)
    missing = {**header, "fields": {k: v for k, v in header["fields"].items() if k != "pid"}}
    extra = {**header, "fields": {**header["fields"], "admin": True}}
    ill = {**header, "fields": {**header["fields"], "pid": "4242"}}
    bad_role = {**header, "fields": {**header["fields"], "role": "actor; rm -rf"}}
    out_of_range = {**header, "fields": {**header["fields"], "pid": -1}}
    for bad, reason in ((missing, "field"), (extra, "field"), (ill, "field"), (bad_role, "field"),
                        (out_of_range, "range")):
        assert _reason(_with_header(frames, bad)) == reason
    with pytest.raises(WireError):
        encode("hello", {"role": "actor"})  # the sender's own bug is caught before sending


def test_rejects_truncated_and_extra_frames():
    frames = _episodes_frames()
    assert _reason(frames[:-1]) == "frame_count"
    assert _reason(frames + [b"\x00" * 8]) == "frame_count"
    weights = encode_weights(1, {"w": np.ones(3)})
    assert _reason([weights, b""]) in ("bad_msgpack", "frame_count")
    assert _reason([weights[:-4]]) == "size"
    assert _reason([weights + b"\x00"]) == "size"


def test_rejects_wrong_dtype_shape_and_sizes():
    frames = _episodes_frames()
    header = _header(frames)
    names = [d[0] for d in header["arrays"]]
    i = names.index("actions")

    def with_desc(desc):
        arrays = list(header["arrays"])
        arrays[i] = desc
        return _with_header(frames, {**header, "arrays": arrays})

    name, dtype, shape, nbytes = header["arrays"][i]
    assert _reason(with_desc([name, "<i8", shape, nbytes * 8])) == "dtype"
    assert _reason(with_desc([name, dtype, [shape[0] + 1], nbytes])) == "shape"
    assert _reason(with_desc([name, dtype, [shape[0] // 2, 2], nbytes])) == "shape"
    assert _reason(with_desc([name, dtype, [2 ** 40], 2 ** 40])) == "size"
    # 2**20 steps is under the byte cap but over the schema's per-dimension cap (MAX_FRAMES).
    assert _reason(with_desc([name, dtype, [2 ** 20], 2 ** 20])) == "shape"
    assert _reason(with_desc([name, dtype, shape, nbytes + 1])) in ("shape", "size")
    frames_short = list(frames)
    frames_short[1 + i] = frames_short[1 + i][:-1]
    assert _reason(frames_short) == "size"


def test_rejects_nan_and_out_of_range_values():
    fields, arrays = _base_batch()
    rewards = arrays["rewards"].copy()
    rewards[3] = np.nan
    assert _reason(_episodes_frames(rewards=rewards)) == "nan"
    rewards[3] = 2.0
    assert _reason(_episodes_frames(rewards=rewards)) == "range"
    actions = arrays["actions"].copy()
    actions[-1] = MAX_ACTIONS  # no world has that action (FetchAttr's 4 and BabyAI's 7 are checked per run)
    assert _reason(_episodes_frames(actions=actions)) == "range"
    frames = arrays["frames"].copy()
    frames[0, 0, 0, 1] = 7  # color channel: 0 none, 1..6
    assert _reason(_episodes_frames(frames=frames)) == "range"
    frames = arrays["frames"].copy()
    frames[1, 2, 3, 0] = MAX_CHANNEL_VALUES[0]  # kind channel: FetchAttr 0..4, BabyAI 0..10
    assert _reason(_episodes_frames(frames=frames)) == "range"
    outcome = arrays["outcome"].copy()
    outcome[0] = 3
    assert _reason(_episodes_frames(outcome=outcome)) == "range"
    picked = arrays["picked"].copy()
    picked[0, 1] = MAX_ATTR_VALUES[1]  # type index: FetchAttr key, ball; BabyAI key, ball, box
    assert _reason(_episodes_frames(picked=picked)) == "range"
    mission = arrays["mission"].copy()
    mission[0, 0] = 5000
    assert _reason(_episodes_frames(mission=mission)) == "range"
    weights = encode_weights(1, {"w": np.array([1.0, np.inf])})
    assert _reason([weights]) == "nan"


def test_rejects_inconsistent_shared_dimensions():
    fields, arrays = pack_episodes(episode_batch(4, seed=2))
    with pytest.raises(WireError) as err:
        encode("episodes", {"count": 5}, arrays)
    assert err.value.reason == "shape"
    frames = [bytes(f) for f in encode("episodes", fields, arrays)]
    header = _header(frames)
    header["fields"]["count"] = 3
    assert _reason(_with_header(frames, header)) == "shape"
    with pytest.raises(WireError) as err:
        encode("episodes", fields, {**arrays, "outcome": arrays["outcome"][:3]})
    assert err.value.reason == "shape"


def test_unpack_checks_the_run_world():
    episodes = episode_batch(4, seed=4)
    msg = decode(encode("episodes", *pack_episodes(episodes)))
    longest = max(ep.length for ep in episodes)
    with pytest.raises(WireError) as err:
        unpack_episodes(msg, replace(SPEC, max_steps=longest - 1))
    assert err.value.reason in ("episode_length", "outcome")
    with pytest.raises(WireError) as err:
        unpack_episodes(msg, replace(SPEC, vocab_size=int(msg.arrays["mission"].max())))
    assert err.value.reason == "mission_token"
    with pytest.raises(WireError) as err:
        unpack_episodes(msg, replace(SPEC, view_size=9))
    assert err.value.reason == "shape"
    with pytest.raises(WireError) as err:
        unpack_episodes(msg, replace(SPEC, mission_len=12))
    assert err.value.reason == "shape"
    with pytest.raises(WireError) as err:
        unpack_episodes(decode(encode("stop")), SPEC)
    assert err.value.reason == "unknown_type"


def test_unpack_rejects_lengths_that_do_not_add_up():
    fields, arrays = pack_episodes(episode_batch(4, seed=5))
    lengths = arrays["lengths"].copy()
    lengths[0] += 1  # one step more than the actions and frames carried
    msg = decode(encode("episodes", fields, {**arrays, "lengths": lengths}))
    with pytest.raises(WireError) as err:
        unpack_episodes(msg, replace(SPEC, max_steps=MAX_STEPS + 1))
    assert err.value.reason == "shape"
