"""The learner's control server over real sockets (loopback TCP), the shared loop helpers, and the
registry's telemetry: hello -> welcome or refuse, the actors' wait for the relabeler, rejoin, the message guard."""
from __future__ import annotations

import logging
import os
import time

import pytest
import zmq

from higher_dist import metrics as m
from higher_dist.config_presets import make_config
from higher_dist.launch.channels import open_channel
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.roles.client import REJOIN
from higher_dist.roles.control_server import ControlServer
from higher_dist.roles.loop import Every, HandlerGuard
from higher_dist.roles.registry import REJECT_STAT_PREFIX, RoleRegistry
from higher_dist.wire import codec, sockets
from higher_dist.wire.schema import PROTOCOL_VERSION
from higher_dist.wire.security import Security


class Peer:
    """A DEALER on the control channel, as a role's ControlClient opens it."""

    def __init__(self, ctx, endpoint: str, role: str):
        self.sock = open_channel(ctx, "control", "connect", endpoint, Security())
        self.role = role

    def send(self, msg_type: str, fields: dict) -> None:
        self.sock.send_multipart(codec.encode(msg_type, fields, sender=self.role))

    def hello(self, index: int = -1, protocol: int = PROTOCOL_VERSION) -> None:
        self.send("hello", {"role": self.role, "host": "here", "pid": os.getpid(), "protocol": protocol,
                            "index": index})

    def reply(self, timeout_ms: int = 300):
        return sockets.recv_message(self.sock, timeout_ms)


@pytest.fixture
def cluster():
    ctx = zmq.Context()
    cfg = make_config("higher", "small", actors=2)
    endpoints = Endpoints.from_base("127.0.0.1", free_base_port())
    rejects = sockets.RejectCounter()
    server = ControlServer(ctx, cfg, endpoints, Security(), None, RoleRegistry(), rejects)
    peers: list[Peer] = []

    def peer(role: str) -> Peer:
        peers.append(Peer(ctx, endpoints.control, role))
        return peers[-1]

    def pump(seconds: float = 0.3) -> None:
        """Let the server handle what has arrived (it never blocks)."""
        end = time.time() + seconds
        while time.time() < end:
            server.poll()
            time.sleep(0.01)

    yield server, peer, pump, endpoints
    for p in peers:
        p.sock.close(linger=0)
    server.sock.close(linger=0)
    ctx.term()


def test_an_actor_is_welcomed_once_the_relabeler_has_registered_its_address(cluster):
    server, peer, pump, endpoints = cluster
    actor, relabeler = peer("actor"), peer("relabeler")
    actor.hello()
    pump()
    assert actor.reply(100) is None and len(server.pending) == 1  # nowhere to send episodes yet
    relabeler.hello(index=0)
    pump()
    welcome = relabeler.reply()
    assert welcome.type == "welcome" and welcome.fields["index"] == 0
    assert welcome.fields["config"]["actors"] == 2
    relabeler.send("register", {"role": "relabeler", "endpoint": "tcp://10.0.0.7:6000"})
    pump()
    welcome = actor.reply()
    assert welcome.type == "welcome" and welcome.fields["index"] == 0
    assert welcome.fields["endpoints"]["episodes"] == "tcp://10.0.0.7:6000"
    assert welcome.fields["endpoints"]["weights"] == endpoints.weights
    assert server.pending == []


def test_another_protocol_version_and_an_unknown_role_are_refused_with_the_reason(cluster):
    _, peer, pump, _ = cluster
    old, stranger = peer("actor"), peer("spy")
    old.hello(protocol=PROTOCOL_VERSION + 1)
    stranger.hello()
    pump()
    refusal = old.reply()
    assert refusal.type == "refuse" and "protocol version mismatch" in refusal.fields["reason"]
    refusal = stranger.reply()
    assert refusal.type == "refuse" and "unknown role 'spy'" in refusal.fields["reason"]


def test_a_peer_that_never_said_hello_is_asked_to_say_it_and_an_actor_cannot_register(cluster):
    server, peer, pump, _ = cluster
    late = peer("actor")
    late.send("heartbeat", {"role": "actor", "id": 0, "state": "running", "counters": {"frames": 1.0}})
    pump()
    refusal = late.reply()
    assert refusal.type == "refuse" and refusal.fields["reason"] == REJOIN
    assert server.rejects.counts()["unknown_peer"] == 1
    late.hello(index=1)
    late.send("register", {"role": "relabeler", "endpoint": "tcp://10.0.0.7:6000"})
    pump()
    assert server.relabeler_endpoint is None and server.rejects.counts()["role_not_allowed"] == 1
    refusal = late.reply()
    assert refusal.type == "refuse" and "may not register the relabeler's address" in refusal.fields["reason"]


def test_stats_and_heartbeats_land_in_the_registry_and_stop_reaches_every_role(cluster):
    server, peer, pump, _ = cluster
    relabeler = peer("relabeler")
    relabeler.hello(index=0)
    pump()
    assert relabeler.reply().type == "welcome"
    relabeler.send("stats", {"role": "relabeler", "id": 0, "values": {"relabels_per_s": 3.5, "reject_cell": 2}})
    relabeler.send("heartbeat", {"role": "relabeler", "id": 0, "state": "running", "counters": {"pid": 77.0}})
    pump()
    info = server.registry.roles[("relabeler", 0)]
    assert info.stats["relabels_per_s"] == 3.5 and info.pid == 77
    server.stop_all("done")
    stop = relabeler.reply()
    assert stop.type == "stop" and stop.fields["reason"] == "done"


def test_the_guard_counts_a_failing_check_by_reason_and_returns_what_a_good_one_returns():
    rejects = sockets.RejectCounter()
    guard = HandlerGuard(rejects, logging.getLogger("test"), "control")
    msg = codec.decode(codec.encode("stop", {"reason": "x"}, sender="actor3"))

    def broken(_msg):
        raise KeyError("boom")

    assert guard(msg, broken, msg) is None and guard(msg, lambda x: x + 1, 1) == 2
    assert guard.errors == 1 and rejects.counts() == {"handler_error": 1}

    def malformed(_msg):
        raise codec.WireError("range", "action 9")

    assert guard(msg, malformed, msg) is None  # a message the wire checks refuse: counted under its reason
    assert guard.errors == 1 and rejects.counts() == {"handler_error": 1, "range": 1}


def test_every_fires_once_a_period_and_due_leaves_it_alone():
    timer = Every(2.0, start=10.0)
    assert not timer(11.0) and timer.due(12.5) and timer.due(12.5)  # due() does not start a new period
    assert timer(12.5) and not timer(14.0) and timer(14.6)
    first = Every(1.0, start=0.0)
    assert first(5.0)  # start=0.0: fires at once


def test_registry_telemetry_sums_every_roles_rejects_and_the_actors_rates():
    reg = RoleRegistry()
    a0 = reg.hello("actor", 0, b"a0", "h", 1)
    a1 = reg.hello("actor", 1, b"a1", "h", 2)
    rl = reg.hello("relabeler", 0, b"r0", "h", 3)
    a0.stats.update({"frames_per_s": 100.0, "weights_version": 90, "epsilon_mean": 0.2, REJECT_STAT_PREFIX + "cell": 2})
    a1.stats.update({"frames_per_s": 50.0, "weights_version": 70, "epsilon_mean": 0.4})
    rl.stats.update({"relabels_per_s": 4.0, REJECT_STAT_PREFIX + "cell": 1, REJECT_STAT_PREFIX + "outcome": 5})
    own = {"role": "learner", "id": 0}
    t = reg.telemetry(own, learner_version=100, own_rejects={"cell": 10})
    assert t[m.REJECTS_BY_REASON] == {"cell": 13, "outcome": 5} and t[m.REJECTED] == 18
    assert t[m.FRAMES_PER_S] == 150.0 and t[m.WEIGHTS_LAG_MEAN] == 20.0 and t[m.EPSILON_MEAN] == pytest.approx(0.3)
    assert t[m.RELABELS_PER_S] == 4.0 and t[m.ROLES][0] is own and len(t[m.ROLES]) == 4
