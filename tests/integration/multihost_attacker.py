"""An outsider on another host, in plain pyzmq (none of the project's socket code): for `seconds` it tries
every channel of a cluster whose control endpoint it knows, and prints what it achieved as JSON.

    python multihost_attacker.py tcp://HEAD:PORT none|DIR SECONDS SERVER_KEY_FILE push|nopush

DIR holds a client pair `client.key_secret` (for the unlisted-key attack: a fresh pair the servers do not
list); SERVER_KEY_FILE is the servers' public key, which an attacker may well know. Per channel it
reports handshakes that succeeded and failed (socket monitor), messages it managed to send (episodes,
hello) and messages it received (welcome, weights, telemetry). `nopush` (for a listed key, the positive
control) only connects the episode channels, so no forged episode enters the run.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np
import zmq
import zmq.auth
from zmq.utils.monitor import recv_monitor_message

# tcp://HOST:P + offset: the layout the cluster documents (the attacker reads docs too).
OFFSETS = {"control": 0, "experience": 1, "weights": 2, "telemetry": 3, "episodes": 4}
KINDS = {"control": zmq.DEALER, "experience": zmq.PUSH, "weights": zmq.SUB, "telemetry": zmq.SUB,
         "episodes": zmq.PUSH}


def forged_messages() -> tuple[list[bytes], list[bytes]]:
    """A well-formed episodes batch of all-ones frames, and a hello: what an outsider would send."""
    from higher_dist.learning.episode import Episode
    from higher_dist.world.spec import SUCCESS
    from higher_dist.wire import PROTOCOL_VERSION, encode, pack_episodes

    length = 9
    episode = Episode(frames=np.ones((length + 1, 7, 7, 4), np.uint8), actions=np.ones(length, np.uint8),
                      rewards=np.ones(length, np.float32), mission=np.ones(10, np.int64), outcome=SUCCESS,
                      picked=np.ones(4, np.int8), goal=np.ones(4, np.int8))
    forged = [bytes(f) for f in encode("episodes", *pack_episodes([episode] * 8), sender="actor0")]
    hello = [bytes(f) for f in encode("hello", {"role": "dashboard", "host": "evil", "pid": 1,
                                                "protocol": PROTOCOL_VERSION, "index": -1}, sender="dashboard")]
    return forged, hello


def main() -> int:
    control, keys, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    server_key, push = sys.argv[4], sys.argv[5] == "push"
    host, port = control.rsplit(":", 1)
    ctx = zmq.Context()
    socks, monitors, report = {}, {}, {}
    for name, offset in OFFSETS.items():
        s = ctx.socket(KINDS[name])
        s.setsockopt(zmq.LINGER, 0)
        if KINDS[name] in (zmq.PUSH, zmq.DEALER):
            s.setsockopt(zmq.IMMEDIATE, 1)  # a send succeeds only onto a completed (authenticated) connection
        if KINDS[name] == zmq.SUB:
            s.setsockopt(zmq.SUBSCRIBE, b"")
        if keys != "none":
            public, secret = zmq.auth.load_certificate(f"{keys}/client.key_secret")
            s.curve_publickey, s.curve_secretkey = public, secret
            s.curve_serverkey = zmq.auth.load_certificate(server_key)[0]
        monitors[name] = s.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_HANDSHAKE_FAILED_AUTH
                                              | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
                                              | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_DISCONNECTED)
        s.connect(f"{host}:{int(port) + offset}")
        socks[name] = s
        report[name] = {"handshakes_ok": 0, "handshakes_failed": 0, "sent": 0, "received": 0}
    forged, hello = forged_messages()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        for name, s in socks.items():
            try:
                if name in ("experience", "episodes") and push:
                    s.send_multipart(forged, zmq.NOBLOCK)
                    report[name]["sent"] += 1
                elif name == "control":
                    s.send_multipart(hello, zmq.NOBLOCK)
                    report[name]["sent"] += 1
            except zmq.Again:
                pass
            while s.poll(0, zmq.POLLIN):
                s.recv_multipart()
                report[name]["received"] += 1
            while monitors[name].poll(0):
                event = recv_monitor_message(monitors[name])["event"]
                if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                    report[name]["handshakes_ok"] += 1
                elif event != zmq.EVENT_DISCONNECTED:
                    report[name]["handshakes_failed"] += 1
        time.sleep(0.05)
    for name, s in socks.items():
        s.disable_monitor()
        monitors[name].close(0)
        s.close(0)
    ctx.term()
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
