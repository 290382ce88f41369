"""What actors and the relabeler share: the control connection to the learner.

`ControlClient.join` says hello and waits for the welcome that carries the run's config and endpoints;
a refusal (e.g. a protocol mismatch) raises `Refused` with the learner's reason. Heartbeats and stats go
up the same DEALER socket; a `stop` coming down it ends the role.
"""
from __future__ import annotations

import logging
import math
import os
import signal
import socket
import time
from typing import Any

import torch
import zmq

from higher_dist import metrics as m
from higher_dist.config import Config, from_dict
from higher_dist.launch.channels import open_channel
from higher_dist.launch.topology import Endpoints
from higher_dist.roles.loop import Every
from higher_dist.wire import codec, sockets
from higher_dist.wire.security import Security
from higher_dist.wire.schema import PROTOCOL_VERSION


# The learner's answer to a peer it does not know (it restarted since that peer's hello).
REJOIN = "unknown peer: say hello first"
HEARTBEAT_EVERY_S = 1.0


class Refused(RuntimeError):
    pass


class ControlClient:
    def __init__(self, learner: str, role: str, index: int | None, security: Security | None = None):
        Endpoints.from_control(learner)  # a malformed address fails here, with its reason
        self.role, self.index = role, -1 if index is None else index
        self.ctx = zmq.Context.instance()
        self.security = security or Security()
        self.sock = open_channel(self.ctx, "control", "connect", learner, self.security)
        self.rejects = sockets.RejectCounter()
        self.stop_reason: str | None = None
        self.restarts = int(os.environ.get("HIGHER_RESTARTS", "0"))
        self._heartbeats = Every(HEARTBEAT_EVERY_S, start=0.0)  # the first one goes at once
        self._seq = 0

    def send(self, msg_type: str, fields: dict[str, Any]) -> None:
        self._seq += 1
        try:
            self.sock.send_multipart(codec.encode(msg_type, fields, sender=self.role, seq=self._seq),
                                     flags=zmq.NOBLOCK)
        except zmq.Again:
            pass  # the learner is gone or slow; heartbeats are periodic, the next one will do

    def join(self, timeout_s: float = 120.0, should_stop=None) -> tuple[Config, Endpoints]:
        """Hello until welcomed; returns the learner's config and endpoints. KeyboardInterrupt when
        `should_stop()` turns true while waiting (a signal arrived)."""
        deadline = time.time() + timeout_s
        self._hello = {"role": self.role, "host": socket.gethostname(), "pid": os.getpid(),
                       "protocol": PROTOCOL_VERSION, "index": self.index}
        while time.time() < deadline:
            self.send("hello", self._hello)
            msg = sockets.recv_message(self.sock, 1000, self.rejects, "control", self._version_error)
            if should_stop is not None and should_stop():
                raise KeyboardInterrupt
            if msg is None:
                continue
            if msg.type == "refuse":
                raise Refused(msg.fields["reason"])
            if msg.type == "welcome":
                if msg.fields["protocol"] != PROTOCOL_VERSION:
                    raise Refused(f"protocol mismatch: learner {msg.fields['protocol']}, this role {PROTOCOL_VERSION}")
                self.index = msg.fields["index"]
                self._hello["index"] = self.index  # a later hello (rejoin) keeps this index
                try:
                    endpoints = Endpoints.from_dict(msg.fields["endpoints"])
                except ValueError as e:
                    raise Refused(f"the learner's welcome has unusable endpoints: {e}") from None
                return from_dict(msg.fields["config"]), endpoints
        raise TimeoutError(f"no welcome from the learner within {timeout_s:.0f} s")

    @staticmethod
    def _version_error(err: codec.WireError, _identity) -> None:
        # The learner answers in its own protocol version; unreadable here means a mismatch.
        if err.reason == "version":
            raise Refused(f"protocol version mismatch: the learner speaks {err.peer_version}, "
                          f"this role speaks {PROTOCOL_VERSION}; run the same higher-dist version everywhere")

    def poll(self) -> bool:
        """Read control messages without blocking; True once the learner said stop."""
        while True:
            msg = sockets.recv_message(self.sock, 0, self.rejects)
            if msg is None:
                return self.stop_reason is not None
            if msg.type == "stop":
                self.stop_reason = msg.fields.get("reason") or "stop"
            elif msg.type == "refuse" and msg.fields["reason"] == REJOIN:
                self.send("hello", self._hello)  # the learner restarted: join it again
            elif msg.type == "refuse":  # e.g. this host's key was revoked: the role ends, saying why
                self.stop_reason = f"refused by the learner: {msg.fields['reason']}"
                logging.getLogger(f"higher.{self.role}").error("%s", self.stop_reason)

    def heartbeat(self, counters: dict[str, float], state: str = "running") -> None:
        """At most one heartbeat a period while running; a change of state goes at once."""
        if state == "running" and not self._heartbeats.due():
            return
        self._heartbeats.reset()
        counters = {**counters, m.ROW_PID: os.getpid()}
        self.send("heartbeat", {"role": self.role, "id": self.index, "state": state,
                                "counters": {k: float(v) for k, v in counters.items()
                                             if v is not None and math.isfinite(float(v))}})

    def stats(self, values: dict[str, Any]) -> None:
        values = {**values, m.ROW_RESTARTS: self.restarts, m.REJECTED: self.rejects.total,
                  **{m.REJECT_STAT_PREFIX + reason: n for reason, n in self.rejects.counts().items()}}
        # The wire refuses NaN/inf; a metric that has none yet travels as nil.
        values = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in values.items()}
        self.send("stats", {"role": self.role, "id": self.index, "values": values})

    def close(self) -> None:
        self.heartbeat({}, state="stopping")
        self.sock.close(linger=200)
        self.security.close()


def start_role(learner: str, role: str, index: int | None, security: Security | None,
               threads: int | None) -> tuple[ControlClient, Config, Endpoints, list]:
    """What every non-head role does first: logging, stop on SIGINT/SIGTERM, join the learner, set
    torch's threads. Returns (client, config, endpoints, stop flag). A refusal ends the process with
    exit code 2 and the learner's reason; a signal while waiting for the welcome ends it with 0."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    stop: list = []
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.append(1))
    client = ControlClient(learner, role, index, security)
    try:
        cfg, endpoints = client.join(should_stop=lambda: bool(stop))
    except Refused as e:
        logging.getLogger(f"higher.{role}").error("the learner refused this %s: %s", role, e)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        raise SystemExit(0) from None
    torch.set_num_threads(threads or 1)  # cfg.torch_threads is the learner's share; a role keeps one
    return client, cfg, endpoints, stop

