"""Socket helpers over real sockets on 127.0.0.1: options, reject counting, routed control, CONFLATE weights, CURVE."""
from __future__ import annotations

import logging
import time

import msgpack
import numpy as np
import pytest
import zmq

from higher_dist.wire import (PROTOCOL_VERSION, RejectCounter, bind_random, encode, encode_weights, make_socket,
                              recv_message, recv_routed, recv_weights, send, send_routed)
from higher_dist.wire.schema import MAX_FRAME_BYTES
from higher_dist.wire.security import CurveClient, CurveServer, generate_keys, start_authenticator


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def _recv_within(sock, counter, seconds=2.0, **kwargs):
    """recv_message until a message or `seconds` pass (delivery over TCP is not instant)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = recv_message(sock, 50, counter, **kwargs)
        if msg is not None:
            return msg
    return None


def test_make_socket_sets_the_options(ctx):
    sock = make_socket(ctx, zmq.PUSH, connect="tcp://127.0.0.1:1", hwm=7, linger_ms=123)
    assert sock.getsockopt(zmq.SNDHWM) == 7 and sock.getsockopt(zmq.RCVHWM) == 7
    assert sock.getsockopt(zmq.LINGER) == 123
    assert sock.getsockopt(zmq.MAXMSGSIZE) == MAX_FRAME_BYTES
    assert sock.getsockopt(zmq.IMMEDIATE) == 1  # a connecting PUSH queues only to live peers
    assert sock.getsockopt(zmq.RECONNECT_IVL_MAX) > sock.getsockopt(zmq.RECONNECT_IVL) > 0  # backoff
    sub = make_socket(ctx, zmq.SUB, conflate=True, connect="tcp://127.0.0.1:1")
    assert sub.getsockopt(zmq.CONFLATE) == 1
    pull = make_socket(ctx, zmq.PULL)
    assert pull.getsockopt(zmq.IMMEDIATE) == 0


def test_recv_message_counts_rejects_and_returns_none(ctx):
    pull = make_socket(ctx, zmq.PULL)
    endpoint = bind_random(pull)
    push = make_socket(ctx, zmq.PUSH, connect=endpoint)
    counter = RejectCounter()
    good = encode("heartbeat", {"role": "actor", "id": 2, "state": "running", "counters": {"frames": 10}},
                  sender="actor-2", seq=1)
    wrong_version = msgpack.packb({**msgpack.unpackb(good[0]), "v": 99})
    truncated = encode("episodes", {"count": 1}, {
        "frames": np.zeros((3, 7, 7, 4), np.uint8), "actions": np.zeros(2, np.uint8),
        "rewards": np.zeros(2, np.float32), "lengths": np.array([2], np.int32),
        "mission": np.zeros((1, 10), np.int64), "outcome": np.array([2], np.uint8),
        "picked": -np.ones((1, 4), np.int8), "goal": np.zeros((1, 4), np.int8), "pick_step": -np.ones(1, np.int32),
        "later_achieved": -np.ones((1, 7, 4), np.int8), "later_step": -np.ones((1, 7), np.int32),
        "relabelled": np.zeros(1, np.uint8), "actor_id": np.zeros(1, np.int32),
        "weights_version": np.zeros(1, np.int64)})[:-3]
    assert send(push, good)
    msg = _recv_within(pull, counter)
    assert msg is not None and msg.type == "heartbeat" and msg.fields["counters"] == {"frames": 10}
    for bad in ([b"\xc1 not msgpack"], [wrong_version], truncated, [b"", b"", b""]):
        assert send(push, bad)
    assert _recv_within(pull, counter, seconds=0.5) is None
    deadline = time.monotonic() + 2
    while counter.total < 4 and time.monotonic() < deadline:
        recv_message(pull, 50, counter)
    assert counter.counts() == {"bad_msgpack": 2, "version": 1, "frame_count": 1}
    assert recv_message(pull, 0, counter) is None  # nothing left: a non-blocking poll returns None


def test_reject_counter_logs_at_a_limited_rate(caplog):
    counter = RejectCounter(log_every_s=60.0)
    with caplog.at_level(logging.WARNING, logger="higher_dist.wire"):
        for _ in range(5):
            counter.add("range", "actions above 3", "experience")
        counter.add("nan", "rewards")
    assert counter.counts() == {"range": 5, "nan": 1} and counter.total == 6
    assert len(caplog.records) == 2  # one per reason, not one per message


def test_router_dealer_routed_helpers(ctx):
    router = make_socket(ctx, zmq.ROUTER)
    endpoint = bind_random(router)
    dealer = make_socket(ctx, zmq.DEALER, connect=endpoint, identity="actor-0")
    send(dealer, encode("hello", {"role": "actor", "host": "here", "pid": 1, "protocol": 1}))
    deadline = time.monotonic() + 2
    got = None
    while got is None and time.monotonic() < deadline:
        got = recv_routed(router, 50)
    assert got is not None
    identity, msg = got
    assert identity == b"actor-0" and msg.type == "hello"
    send_routed(router, identity, encode("refuse", {"reason": "full"}))
    reply = _recv_within(dealer, RejectCounter())
    assert reply is not None and reply.fields["reason"] == "full"


def test_on_reject_lets_the_learner_refuse_another_protocol_version(ctx):
    router = make_socket(ctx, zmq.ROUTER)
    endpoint = bind_random(router)
    dealer = make_socket(ctx, zmq.DEALER, connect=endpoint)
    hello = encode("hello", {"role": "actor", "host": "here", "pid": 1, "protocol": 1})
    send(dealer, [msgpack.packb({**msgpack.unpackb(hello[0]), "v": 7})])

    def refuse(error, identity):
        if error.reason == "version":
            send_routed(router, identity, encode("refuse", {
                "reason": f"peer speaks protocol {error.peer_version}, learner speaks {PROTOCOL_VERSION}",
                "protocol": PROTOCOL_VERSION}))

    counter = RejectCounter()
    deadline = time.monotonic() + 2
    while counter.total == 0 and time.monotonic() < deadline:
        assert recv_routed(router, 50, counter, on_reject=refuse) is None
    reply = _recv_within(dealer, RejectCounter())
    assert counter.counts() == {"version": 1}
    assert reply is not None and reply.type == "refuse" and "protocol 7" in reply.fields["reason"]


def test_weights_conflate_subscriber_gets_the_latest_version(ctx):
    pub = make_socket(ctx, zmq.PUB)
    endpoint = bind_random(pub)
    sub = make_socket(ctx, zmq.SUB, connect=endpoint, conflate=True)
    shapes = {"w": (8, 8), "b": (8,)}
    counter = RejectCounter()

    def weights(version):
        return encode_weights(version, {"w": np.full((8, 8), version, np.float32), "b": np.zeros(8, np.float32)})

    deadline = time.monotonic() + 3
    while recv_weights(sub, shapes, 20, counter) is None:  # PUB drops messages until the SUB has joined
        assert time.monotonic() < deadline, "subscriber never joined"
        send(pub, [weights(0)])
    for version in range(1, 51):
        send(pub, [weights(version)])
    time.sleep(0.3)
    got = recv_weights(sub, shapes, 500, counter)
    assert got is not None
    version, arrays = got
    assert version == 50 and np.all(arrays["w"] == 50)
    assert recv_weights(sub, shapes, 50, counter) is None  # CONFLATE kept only the newest
    send(pub, [encode_weights(51, {"w": np.zeros((4, 4), np.float32)})])  # wrong shapes for this network
    assert recv_weights(sub, shapes, 1000, counter) is None
    assert counter.counts() == {"field": 1}


def test_curve_allows_listed_clients_only(ctx, tmp_path):
    keys = tmp_path / "keys"
    generate_keys(keys)
    intruder_keys = tmp_path / "intruder"
    generate_keys(intruder_keys)  # a valid key pair that is not on the server's allow-list
    auth = start_authenticator(ctx, keys)
    try:
        pull = make_socket(ctx, zmq.PULL, curve=CurveServer(str(keys)))
        endpoint = bind_random(pull)
        clients = {
            "listed": CurveClient(str(keys)),
            "unlisted": CurveClient(str(intruder_keys), server_public=str(keys / "server.key")),
            "plain": None,
        }
        received = {}
        for name, curve in clients.items():
            push = make_socket(ctx, zmq.PUSH, connect=endpoint, curve=curve, immediate=False, linger_ms=0)
            send(push, encode("stop", {"reason": name}), zmq.NOBLOCK)
            msg = _recv_within(pull, RejectCounter(), seconds=2.0 if name == "listed" else 0.5)
            received[name] = msg.fields["reason"] if msg is not None else None
            push.close(linger=0)
        assert received == {"listed": "listed", "unlisted": None, "plain": None}
    finally:
        auth.stop()
