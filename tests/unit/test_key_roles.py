"""One key pair per host or role, over real CURVE sockets on 127.0.0.1: the allow-list names each key with
the roles it may take, the learner's control server binds a hello and a `register` to the key that sent
it, a key reaches only its roles' channels, and a revoked key (its entry moved out of allowed_clients/)
gets nothing, without a restart of the learner."""
from __future__ import annotations

import os
import shutil
import stat
import time

import pytest
import zmq

from higher_dist.cli import keys_main
from higher_dist.config_presets import make_config
from higher_dist.launch.channels import open_channel
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.roles.control_server import ControlServer
from higher_dist.roles.registry import RoleRegistry
from higher_dist.wire import codec, sockets
from higher_dist.wire.allowlist import client_key_name, read_allow_list
from higher_dist.wire.schema import PROTOCOL_VERSION
from higher_dist.wire.security import Security, generate_keys


@pytest.fixture
def keys(tmp_path):
    root = tmp_path / "keys"
    for name, role in (("nodeA", "relabeler"), ("nodeB", "actor"), ("nodeC", "actor")):
        assert keys_main([str(root), "--client", name, "--role", role]) == 0
    return root


class Peer:
    def __init__(self, ctx, endpoint: str, role: str, keys, name: str):
        self.sock = open_channel(ctx, "control", "connect", endpoint, Security(str(keys), client_name=name))
        self.sock.setsockopt(zmq.SNDTIMEO, 2000)  # a refused key never gets a pipe: a send must not hang
        self.role = role

    def send(self, msg_type: str, fields: dict) -> None:
        self.sock.send_multipart(codec.encode(msg_type, fields, sender=self.role))

    def hello(self, role: str | None = None) -> None:
        self.send("hello", {"role": role or self.role, "host": "here", "pid": os.getpid(),
                            "protocol": PROTOCOL_VERSION, "index": -1})

    def reply(self, timeout_ms: int = 300):
        return sockets.recv_message(self.sock, timeout_ms)


@pytest.fixture
def learner(keys):
    ctx = zmq.Context()
    endpoints = Endpoints.from_base("127.0.0.1", free_base_port())
    security = Security(str(keys))
    server = ControlServer(ctx, make_config("higher", "small", actors=2), endpoints, security, None,
                           RoleRegistry(), sockets.RejectCounter())
    peers = []

    def peer(role: str, name: str) -> Peer:
        peers.append(Peer(ctx, endpoints.control, role, keys, name))
        return peers[-1]

    def pump(seconds: float = 0.4) -> None:
        end = time.time() + seconds
        while time.time() < end:
            server.poll()
            time.sleep(0.01)

    yield server, peer, pump, (ctx, security), endpoints
    for p in peers:
        p.sock.close(linger=0)
    server.close()
    security.close()
    ctx.term()


def test_higher_keys_makes_a_named_pair_per_host_listed_with_its_roles(keys, capsys):
    grants = {g.name: sorted(g.roles) for g in read_allow_list(keys / "allowed_clients").values()}
    assert grants == {"nodeA": ["relabeler"], "nodeB": ["actor"], "nodeC": ["actor"]}
    assert not (keys / "client.key").exists()  # no shared pair unless asked for
    for path in [*keys.glob("*.key*"), *(keys / "allowed_clients").glob("*")]:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert stat.S_IMODE(keys.stat().st_mode) == 0o700
    assert keys_main([str(keys), "--client", "nodeD"]) == 2  # a named key needs its roles
    assert "--client NAME and --role ROLES go together" in capsys.readouterr().err
    assert keys_main([str(keys), "--client", "nodeD", "--role", "admin"]) == 2
    assert "roles 'admin'" in capsys.readouterr().err
    # Which pair a role uses: the one named after it, the shared one, the only one; else --key.
    assert client_key_name(keys, "actor", "nodeB") == "nodeB"
    with pytest.raises(ValueError, match="several client key pairs .* --key NAME"):
        client_key_name(keys, "actor")
    assert client_key_name(keys, "dashboard") == "nodeA"  # any listed key may read telemetry


def test_an_actors_key_cannot_say_hello_as_the_relabeler_or_register_its_address(learner):
    server, peer, pump, _, _ = learner
    impostor = peer("relabeler", "nodeB")  # an actor host's key
    impostor.hello()
    pump()
    refusal = impostor.reply()
    assert refusal.type == "refuse" and "'nodeB' may take the role(s) actor, not relabeler" in refusal.fields["reason"]
    assert server.rejects.counts()["role_not_allowed"] == 1 and server.registry.roles == {}
    actor = peer("actor", "nodeB")
    actor.hello()  # as itself it is heard (and waits for the relabeler)
    pump()
    assert len(server.pending) == 1
    actor.send("register", {"role": "relabeler", "endpoint": "tcp://10.9.9.9:6000"})
    pump()
    refusal = actor.reply()
    assert refusal.type == "refuse" and "may not register the relabeler's address" in refusal.fields["reason"]
    assert server.rejects.counts()["role_not_allowed"] == 2 and server.relabeler_endpoint is None
    # The relabeler's own key registers, and the waiting actor is welcomed with that address.
    relabeler = peer("relabeler", "nodeA")
    relabeler.hello()
    pump()
    assert relabeler.reply().type == "welcome"
    relabeler.send("register", {"role": "relabeler", "endpoint": "tcp://127.0.0.1:6001"})
    pump()
    assert server.relabeler_endpoint == "tcp://127.0.0.1:6001"
    welcome = actor.reply()
    assert welcome.type == "welcome" and welcome.fields["endpoints"]["episodes"] == "tcp://127.0.0.1:6001"
    assert server.rejects.counts()["role_not_allowed"] == 2


def test_a_revoked_key_gets_nothing_without_a_restart_of_the_learner(learner, keys):
    server, peer, pump, (ctx, security), endpoints = learner
    actor, other = peer("actor", "nodeB"), peer("actor", "nodeC")
    relabeler = peer("relabeler", "nodeA")
    for p in (relabeler, actor, other):
        p.hello()
    pump()
    relabeler.send("register", {"role": "relabeler", "endpoint": "tcp://127.0.0.1:6001"})
    pump()
    assert actor.reply().type == "welcome" and other.reply().type == "welcome"
    (keys / "revoked").mkdir()
    shutil.move(keys / "allowed_clients" / "nodeB.key", keys / "revoked" / "nodeB.key")  # the revoke
    time.sleep(1.1)  # the control channel reads the folder again at most once a second
    actor.send("heartbeat", {"role": "actor", "id": 0, "state": "running", "counters": {"frames": 1.0}})
    pump()
    refusal = actor.reply()
    assert refusal.type == "refuse" and "revoked" in refusal.fields["reason"]
    assert server.rejects.counts()["key_revoked"] == 1
    assert [i.stopped for i in server.registry.roles.values() if i.role == "actor"].count(True) == 1
    # A new connection with the revoked key completes no handshake: no reply on control, no weights.
    again = peer("actor", "nodeB")
    try:
        again.hello()
    except zmq.Again:
        pass  # no handshake, so no pipe to queue the hello on: refused before a byte reaches the server
    pump()
    assert again.reply(500) is None
    weights = open_channel(ctx, "weights", "bind", endpoints.weights, security)  # the learner's authenticator
    subs = {name: open_channel(ctx, "weights", "connect", endpoints.weights, Security(str(keys), client_name=name))
            for name in ("nodeB", "nodeC")}
    for sub in subs.values():
        sub.setsockopt(zmq.SUBSCRIBE, b"")
    time.sleep(0.5)
    for _ in range(10):
        weights.send(b"w")
        time.sleep(0.05)
    assert subs["nodeC"].poll(1000) and not subs["nodeB"].poll(300)
    # The other keys are untouched, and the revoked name cannot be made again by mistake.
    other.send("heartbeat", {"role": "actor", "id": 1, "state": "running", "counters": {"frames": 1.0}})
    pump()
    assert other.reply(200) is None and server.rejects.counts()["key_revoked"] == 1
    with pytest.raises(ValueError, match="nodeB: revoked"):
        generate_keys(keys, clients=("nodeB",))
    for sock in (weights, *subs.values()):
        sock.close(linger=0)


def test_a_key_reaches_only_the_channels_of_its_roles(keys, tmp_path):
    """An actor's key cannot push episodes into the learner's replay (the experience channel is the
    relabeler's), whatever it says in a hello."""
    ctx = zmq.Context()
    endpoint = Endpoints.from_base("127.0.0.1", free_base_port()).experience
    server_security = Security(str(keys))
    pull = open_channel(ctx, "experience", "bind", endpoint, server_security)
    got = {}
    try:
        for name in ("nodeB", "nodeA"):
            push = open_channel(ctx, "experience", "connect", endpoint, Security(str(keys), client_name=name))
            push.send(name.encode(), zmq.NOBLOCK) if push.poll(2000, zmq.POLLOUT) else None
            got[name] = pull.recv() if pull.poll(1500) else None
            push.close(linger=0)
        assert got == {"nodeB": None, "nodeA": b"nodeA"}
    finally:
        pull.close(linger=0)
        server_security.close()
        ctx.term()
