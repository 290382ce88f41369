"""Channels declared once, opened by name, over real sockets on 127.0.0.1: CURVE on every socket under keys,
the experience path's real high-water marks with an authenticator, refusals of unsafe binds, key modes."""
from __future__ import annotations

import dataclasses
import logging
import os
import stat
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from higher_dist.launch.channels import (CHANNELS, EXPERIENCE_HWM, PORT_SPAN, InsecureBind, check_exposure, is_loopback,
                                        open_channel)
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.learning.episode import Episode
from higher_dist.world.spec import SUCCESS
from higher_dist.wire import MESSAGE_TYPES, encode, pack_episodes, recv_message
from higher_dist.wire.security import Security, generate_keys


@pytest.fixture
def keys(tmp_path):
    generate_keys(tmp_path / "keys")
    return str(tmp_path / "keys")


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def episodes_message(n: int, seed: int) -> list:
    """A real multi-frame episodes message (header + 8 array frames)."""
    rng = np.random.default_rng(seed)
    episodes = []
    for _ in range(n):
        length = int(rng.integers(3, 10))
        frames = np.stack([rng.integers(0, [5, 7, 6, 6], size=(7, 7, 4)) for _ in range(length + 1)]).astype(np.uint8)
        rewards = np.zeros(length, np.float32)
        rewards[-1] = 1.0
        episodes.append(Episode(frames=frames, actions=rng.integers(0, 4, length).astype(np.uint8), rewards=rewards,
                                mission=rng.integers(0, 20, 10).astype(np.int64), outcome=SUCCESS,
                                picked=np.array([2, 1, 0, 4], np.int8), goal=np.array([2, 1, 0, 4], np.int8)))
    return encode("episodes", *pack_episodes(episodes), sender="test")


def test_free_port_ranges_are_free_and_below_the_ephemeral_ports_of_outgoing_connections():
    low = 32_768  # Linux's first ephemeral port; /proc says where this machine's range starts
    ephemeral = Path("/proc/sys/net/ipv4/ip_local_port_range")
    if ephemeral.exists():
        low = min(low, int(ephemeral.read_text().split()[0]))
    for _ in range(50):
        base = free_base_port()
        assert 1024 < base and base + PORT_SPAN <= low, base
    with zmq.Context() as context:  # free: every port of the range binds
        socks = [context.socket(zmq.PULL) for _ in range(PORT_SPAN)]
        try:
            for i, sock in enumerate(socks):
                sock.bind(f"tcp://127.0.0.1:{base + i}")
        finally:
            for sock in socks:
                sock.close(linger=0)


def test_every_channel_has_one_endpoint_and_distinct_ports():
    field_names = {f.name for f in dataclasses.fields(Endpoints)}
    assert field_names == set(CHANNELS)
    for channel in CHANNELS.values():
        assert set(channel.messages) <= set(MESSAGE_TYPES), channel.name
    ends = Endpoints.from_base("10.1.2.3", 7000)
    ports = [int(ends[name].rsplit(":", 1)[1]) for name in CHANNELS]
    assert sorted(ports) == list(range(7000, 7000 + len(CHANNELS)))
    assert Endpoints.from_dict(ends.as_dict()) == ends
    moved = ends.with_endpoint("episodes", "tcp://10.9.9.9:6000")
    assert moved.episodes == "tcp://10.9.9.9:6000" and moved.control == ends.control
    with pytest.raises(ValueError, match="tcp://HOST:PORT"):
        ends.with_endpoint("episodes", "10.9.9.9:6000")
    with pytest.raises(ValueError, match="unknown channel 'bogus'"):
        open_channel(zmq.Context.instance(), "bogus", "bind", ends.control, Security())


@pytest.mark.parametrize("name", ["experience", "episodes"])
def test_keys_with_the_real_hwm_deliver_every_multiframe_message(ctx, keys, name):
    """The experience path with keys: RCVHWM/SNDHWM 1, an authenticator, 8-frame messages. Before the fix the
    ZAP user id's credential message held the single slot and 0 of 5 arrived (POLLIN, then EAGAIN)."""
    assert CHANNELS[name].bind_hwm == EXPERIENCE_HWM == 1
    binder, connector = Security(keys), Security(keys)
    endpoint = f"tcp://127.0.0.1:{free_base_port()}"
    pull = open_channel(ctx, name, "bind", endpoint, binder)
    push = open_channel(ctx, name, "connect", endpoint, connector)
    try:
        assert pull.getsockopt(zmq.RCVHWM) == 1 and push.getsockopt(zmq.SNDHWM) == 1
        messages = [episodes_message(3, seed) for seed in range(5)]
        assert all(len(m) > 2 for m in messages)
        received, deadline, pending = [], time.monotonic() + 10, list(messages)
        while len(received) < len(messages) and time.monotonic() < deadline:
            if pending and push.poll(10, zmq.POLLOUT):
                try:
                    push.send_multipart(pending[0], flags=zmq.NOBLOCK, copy=False)
                    pending.pop(0)
                except zmq.Again:
                    pass
            msg = recv_message(pull, 10)
            if msg is not None:
                received.append(msg)
        assert len(received) == 5, f"{len(received)} of 5 episode messages arrived through CURVE with HWM 1"
        assert [m.fields["count"] for m in received] == [3] * 5
    finally:
        push.close(0)
        pull.close(0)
        binder.close()


def test_under_keys_every_socket_is_curve_and_every_binder_authenticates(ctx, keys):
    security = Security(keys)
    base = free_base_port()
    ends = Endpoints.from_base("127.0.0.1", base)
    opened = []
    try:
        for name in CHANNELS:
            bound = open_channel(ctx, name, "bind", ends[name], security)
            connected = open_channel(zmq.Context.instance(), name, "connect", ends[name], security)
            opened += [bound, connected]
            assert bound.getsockopt(zmq.CURVE_SERVER) == 1, name
            assert connected.getsockopt(zmq.CURVE_SERVER) == 0 and connected.getsockopt(zmq.MECHANISM) == zmq.CURVE
            assert bound.getsockopt(zmq.MECHANISM) == zmq.CURVE
        assert len(security._auths) == 1  # one authenticator for the binding context, started on first bind
    finally:
        for s in opened:
            s.close(0)
        security.close()


def test_telemetry_reaches_listed_subscribers_only(ctx, tmp_path, keys):
    intruder = tmp_path / "intruder"
    generate_keys(intruder)
    learner = Security(keys)
    endpoint = f"tcp://127.0.0.1:{free_base_port()}"
    pub = open_channel(ctx, "telemetry", "bind", endpoint, learner)
    subs = {
        "listed": open_channel(ctx, "telemetry", "connect", endpoint, Security(keys)),
        "unlisted": open_channel(ctx, "telemetry", "connect", endpoint, Security(str(intruder))),
        "plain": open_channel(ctx, "telemetry", "connect", endpoint, Security()),
    }
    try:
        got = {name: 0 for name in subs}
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            pub.send(b"\x81\xa6frames\x01")
            for name, sub in subs.items():
                while sub.poll(0):
                    sub.recv()
                    got[name] += 1
            time.sleep(0.05)
        assert got["listed"] > 0 and got["unlisted"] == 0 and got["plain"] == 0, got
    finally:
        for s in (pub, *subs.values()):
            s.close(0)
        learner.close()


def test_binding_beyond_loopback_without_keys_is_refused_unless_insecure(ctx, keys, caplog):
    base = free_base_port("0.0.0.0")
    endpoint = f"tcp://127.0.0.1:{base}"
    with pytest.raises(InsecureBind, match=rf"experience 0\.0\.0\.0:{base}.*--keys.*--insecure"):
        open_channel(ctx, "experience", "bind", endpoint, Security(), bind_host="0.0.0.0")
    with caplog.at_level(logging.WARNING, logger="higher_dist.channels"):
        sock = open_channel(ctx, "experience", "bind", endpoint, Security(insecure=True), bind_host="0.0.0.0")
    sock.close(0)
    assert f"experience 0.0.0.0:{base}" in caplog.text and "INSECURE" in caplog.text
    # Loopback needs nothing; keys make any interface fine (other ports: close() releases them lazily).
    open_channel(ctx, "experience", "bind", f"tcp://127.0.0.1:{base + 1}", Security()).close(0)
    secured = Security(keys)
    open_channel(ctx, "experience", "bind", f"tcp://127.0.0.1:{base + 2}", secured, bind_host="0.0.0.0").close(0)
    secured.close()
    with pytest.raises(InsecureBind, match="control \\*:5555, weights \\*:5557"):
        check_exposure({"control": "tcp://*:5555", "weights": "tcp://*:5557"}, Security())
    insecure, caplog_records = Security(insecure=True), len(caplog.records)
    with caplog.at_level(logging.WARNING, logger="higher_dist.channels"):
        check_exposure({"control": "tcp://*:5555", "weights": "tcp://*:5557"}, insecure)
        check_exposure({"control": "tcp://*:5555"}, insecure)  # e.g. when the socket itself is opened
    assert len(caplog.records) == caplog_records + 1  # each exposed port is named once, not per check


def test_is_loopback():
    assert is_loopback("127.0.0.1") and is_loopback("127.5.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert is_loopback("[::1]")
    for exposed in ("0.0.0.0", "*", "10.0.0.1", "::", "eth0", "192.168.1.20"):
        assert not is_loopback(exposed), exposed


def test_secret_keys_are_0600_whatever_the_umask(tmp_path):
    old = os.umask(0o000)
    try:
        generate_keys(tmp_path / "k")
    finally:
        os.umask(old)
    for secret in (tmp_path / "k").glob("*.key_secret"):
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600, secret
    client_secret = tmp_path / "k" / "client.key_secret"
    os.chmod(client_secret, 0o644)  # loosened by hand, or written by an older version
    generate_keys(tmp_path / "k")  # rerun: keeps the keys, tightens the mode
    assert stat.S_IMODE(client_secret.stat().st_mode) == 0o600
    assert sorted(p.name for p in (tmp_path / "k" / "allowed_clients").iterdir()) == ["client.key"]


def test_missing_key_files_are_named(ctx, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="allowed_clients holds no client keys"):
        open_channel(ctx, "control", "bind", f"tcp://127.0.0.1:{free_base_port()}", Security(str(tmp_path / "empty")))
    with pytest.raises(ValueError, match="no client key pair"):
        open_channel(ctx, "control", "connect", "tcp://127.0.0.1:1", Security(str(tmp_path / "empty")))


def test_roles_make_sockets_only_through_open_channel():
    """So that under --keys no socket can be made without CURVE by mistake."""
    import re
    from pathlib import Path

    import higher_dist

    root = Path(higher_dist.__file__).parent
    offenders = []
    for path in [*sorted((root / "roles").glob("*.py")), *sorted((root / "launch").glob("*.py"))]:
        if path.name == "channels.py":
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"make_socket\(|\.socket\(zmq\.|CurveServer|CurveClient|start_authenticator", line):
                offenders.append(f"{path.name}:{n}: {line.strip()}")
    assert offenders == []
