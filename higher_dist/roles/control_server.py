"""The learner's side of the control channel, the mirror of client.py: hello -> welcome or refuse,
register, heartbeats, stats, stop.

A hello of this protocol version from a known role kind gets a number from the registry and a welcome
with the run's config and endpoints. An actor's welcome waits until the relabeler has registered its
episodes address (the actor sends there), so early actors are kept in `pending` and welcomed then. A
peer that speaks another protocol version cannot be decoded but is told why; a peer that never said
hello (the learner restarted since) is asked to say it again (`REJOIN`). Replies never block: a peer
that does not read its socket loses the reply and asks again.

Under --keys every message carries the public key its sender's handshake proved, and the allow-list
(wire/allowlist.py, read again at most once a second) says which roles that key may take: a hello as
another role, or a `register` of the relabeler's address from a key that may not be the relabeler, is
refused with the reason and counted (`role_not_allowed`); a message from a key removed from the list
since its handshake is refused and counted (`key_revoked`), and its role is marked stopped.
"""
from __future__ import annotations

import zmq

from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.launch.channels import open_channel
from higher_dist.launch.topology import Endpoints
from higher_dist.roles.client import REJOIN
from higher_dist.roles.registry import NoSlot, RoleRegistry
from higher_dist.wire import codec, sockets
from higher_dist.wire.schema import PROTOCOL_VERSION
from higher_dist.wire.security import Security

ROLE_KINDS = ("actor", "relabeler", "dashboard")  # the roles that may say hello


class ControlServer:
    def __init__(self, ctx: zmq.Context, cfg: Config, endpoints: Endpoints, security: Security,
                 bind_host: str | None, registry: RoleRegistry, rejects: sockets.RejectCounter):
        self.cfg, self.endpoints, self.registry, self.rejects = cfg, endpoints, registry, rejects
        self.sock = open_channel(ctx, "control", "bind", endpoints.control, security, bind_host)
        self.allow_list = security.allow_list()  # None without keys: loopback, every role allowed
        self.relabeler_endpoint: str | None = None
        self.pending: list[tuple[bytes, int]] = []  # actors' hellos waiting for the relabeler

    def send(self, identity: bytes, msg_type: str, fields: dict) -> None:
        sockets.send_routed(self.sock, identity, codec.encode(msg_type, fields, sender="learner"), zmq.NOBLOCK)

    def welcome(self, identity: bytes, index: int) -> None:
        eps = self.endpoints
        if self.relabeler_endpoint is not None:
            eps = eps.with_endpoint("episodes", self.relabeler_endpoint)
        self.send(identity, "welcome", {"config": self.cfg.to_dict(), "endpoints": eps.as_dict(),
                                        "protocol": PROTOCOL_VERSION, "index": index})

    def capacity(self, role: str) -> int | None:
        """How many of a role the run has numbers for (actors: the config's count; dashboards: any)."""
        return {"actor": self.cfg.actors, "relabeler": 1}.get(role)

    def poll(self, limit: int = 100) -> None:
        """Handle up to `limit` waiting messages without blocking. A message that fails decoding is dropped
        and counted there (wire/sockets.py); one that passed is fully typed by its schema, and `handle`
        answers what a peer may not do with a refusal it counts. So an exception of `handle` is the
        learner's own (an internal error), not the peer's."""
        for _ in range(limit):
            if not self.sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                return
            routed = sockets.recv_routed_from(self.sock, 0, self.rejects, "control", self.refuse_version)
            if routed is not None:
                self.handle(*routed)

    def refuse(self, identity: bytes, reason: str, detail: str) -> None:
        """A refusal the peer is told and the learner counts; never fatal to either."""
        self.rejects.add(reason, detail, "control")
        self.send(identity, "refuse", {"reason": detail})

    def handle(self, identity: bytes, msg, key: str = "") -> None:
        grant = None
        if self.allow_list is not None:
            grant = self.allow_list.grant(key)
            if grant is None:  # listed at its handshake, deleted from allowed_clients/ since
                info = self.registry.seen(identity)
                if info is not None:
                    info.stopped = True
                self.refuse(identity, "key_revoked", f"this key ({key}) is no longer in the learner's "
                            "allowed_clients/: it was revoked")
                return
        if msg.type == "hello":
            role = msg.fields["role"]
            if grant is not None and role in ROLE_KINDS and not grant.may(role):
                self.refuse(identity, "role_not_allowed", f"the key {grant.name!r} may take the role(s) "
                            f"{grant.describe()}, not {role}; give this host a {role} key (higher-keys DIR "
                            f"--client NAME --role {role}) and list it in the learner's allowed_clients/")
                return
            self.hello(identity, msg.fields)
            return
        info = self.registry.seen(identity)
        if info is None:
            # Only a peer that said hello is heard; the client says hello again on this reply.
            self.rejects.add("unknown_peer")
            self.send(identity, "refuse", {"reason": REJOIN})
            return
        f = msg.fields
        if msg.type == "register":  # repeated by the relabeler, so a restarted learner learns it again
            if info.role != "relabeler" or (grant is not None and not grant.may("relabeler")):
                who = f"the key {grant.name!r} ({grant.describe()})" if grant is not None else f"a {info.role}"
                self.refuse(identity, "role_not_allowed", f"{who} may not register the relabeler's address; "
                            "only the relabeler, with a key that may take that role, registers it")
                return
            self.register(info.role, f["endpoint"])
        elif msg.type == "heartbeat":
            info.stopped = f["state"] == "stopping"
            info.stats.update(f["counters"])
            info.pid = int(f["counters"].get(m.ROW_PID, info.pid))
        elif msg.type == "stats":
            info.stats.update(f["values"])
        else:
            self.rejects.add("unexpected_type")

    def hello(self, identity: bytes, f: dict) -> None:
        if f["protocol"] != PROTOCOL_VERSION:
            self.refuse_version_to(identity, f["protocol"])
            return
        if f["role"] not in ROLE_KINDS:
            self.send(identity, "refuse", {"reason": f"unknown role {f['role']!r}"})
            return
        try:
            index = self.registry.assign(f["role"], identity, f["index"], self.capacity(f["role"]))
        except NoSlot as e:
            self.send(identity, "refuse", {"reason": str(e)})
            return
        self.registry.hello(f["role"], index, identity, f["host"], f["pid"])
        if f["role"] == "actor" and self.relabeler_endpoint is None:
            if (identity, index) not in self.pending:  # answered once the relabeler registers
                self.pending.append((identity, index))
        else:
            self.welcome(identity, index)

    def register(self, role: str, endpoint: str) -> None:
        if role != "relabeler":
            self.rejects.add("field")
            return
        try:
            self.endpoints.with_endpoint("episodes", endpoint)
        except ValueError:
            self.rejects.add("field")
            return
        self.relabeler_endpoint = endpoint
        for identity, index in self.pending:
            self.welcome(identity, index)
        self.pending.clear()

    def refuse_version(self, err: codec.WireError, identity: bytes | None) -> None:
        """A peer of another protocol version cannot be decoded, but it can be told why."""
        if err.reason == "version" and identity is not None:
            self.refuse_version_to(identity, err.peer_version)

    def refuse_version_to(self, identity: bytes, peer_version) -> None:
        self.send(identity, "refuse", {
            "reason": f"protocol version mismatch: this learner speaks {PROTOCOL_VERSION}, the peer "
                      f"speaks {peer_version}; run the same higher-dist version everywhere",
            "protocol": PROTOCOL_VERSION})

    def stop_all(self, reason: str) -> None:
        for identity in self.registry.identities():
            self.send(identity, "stop", {"reason": reason})

    def close(self) -> None:
        self.sock.close(linger=200)
