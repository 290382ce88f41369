"""Every channel of the cluster, declared once, and the one function that opens a socket on one.

A channel is a socket pair between two roles: who binds it (and is its CURVE server), who connects (the
CURVE clients), the socket kinds, queue limits, kernel buffers, CONFLATE and the message types it carries.
Roles never create sockets themselves: `open_channel(ctx, name, side, endpoint, security)` makes the
socket as declared here, so under --keys every socket is encrypted and every binder authenticates
against the allow-list, and without keys nothing binds beyond loopback unless the user said --insecure.

    control     base      learner ROUTER <- DEALER actor, relabeler   hello/welcome, register, heartbeats, stats, stop
    experience  base + 1  learner PULL   <- PUSH relabeler            episodes (originals and relabelled copies)
    weights     base + 2  learner PUB    -> SUB actor (CONFLATE)      versioned Q-network weights, one frame
    telemetry   base + 3  learner PUB    -> SUB dashboard (CONFLATE)  one telemetry record per refresh, stop
    episodes    base + 4  relabeler PULL <- PUSH actor                episodes from actors

The episodes channel is the relabeler's: it may run on another host and advertise its own address
(`register`); the learner's welcome then carries that address under the channel's name.
"""
from __future__ import annotations

import ipaddress
import logging
import socket as pysocket
from dataclasses import dataclass
from typing import Literal

import zmq

from higher_dist.launch.addresses import bind_address, parse_endpoint
from higher_dist.wire import sockets
from higher_dist.wire.security import Security

log = logging.getLogger("higher_dist.channels")

# The experience path (actor -> relabeler -> learner) holds little in flight, so the learner's rate
# limiter reaches the actors within a few batches and the replay never trains on stale experience.
# (A queue of 1 is only safe because the authenticator sends no user id: see security.Security.)
EXPERIENCE_HWM = 1  # messages (episode batches) per socket queue
EXPERIENCE_BUFFER = 64 << 10  # bytes of kernel socket buffer


@dataclass(frozen=True)
class Channel:
    name: str
    port_offset: int  # from the cluster's base port
    binder: str  # the role that binds: the CURVE server, which authenticates its clients
    connectors: tuple[str, ...]  # the roles that connect: CURVE clients
    bind_kind: int
    connect_kind: int
    messages: tuple[str, ...]  # the message types it carries (wire/schema.py)
    bind_hwm: int
    connect_hwm: int
    kernel_buffer: int | None = None  # SO_SNDBUF/SO_RCVBUF where backpressure must be prompt
    conflate: bool = False  # the connecting SUB keeps only the newest message
    connect_linger_ms: int = 200


CHANNELS: dict[str, Channel] = {c.name: c for c in (
    Channel("control", 0, "learner", ("actor", "relabeler"), zmq.ROUTER, zmq.DEALER,
            ("hello", "welcome", "refuse", "register", "heartbeat", "stats", "stop"), bind_hwm=1000, connect_hwm=100),
    Channel("experience", 1, "learner", ("relabeler",), zmq.PULL, zmq.PUSH, ("episodes",),
            bind_hwm=EXPERIENCE_HWM, connect_hwm=EXPERIENCE_HWM, kernel_buffer=EXPERIENCE_BUFFER),
    Channel("weights", 2, "learner", ("actor",), zmq.PUB, zmq.SUB, ("weights",),
            bind_hwm=2, connect_hwm=2, conflate=True, connect_linger_ms=0),
    Channel("telemetry", 3, "learner", ("dashboard",), zmq.PUB, zmq.SUB, ("telemetry", "stop"),
            bind_hwm=10, connect_hwm=4, conflate=True, connect_linger_ms=0),
    Channel("episodes", 4, "relabeler", ("actor",), zmq.PULL, zmq.PUSH, ("episodes",),
            bind_hwm=EXPERIENCE_HWM, connect_hwm=EXPERIENCE_HWM, kernel_buffer=EXPERIENCE_BUFFER),
)}
PORT_SPAN = max(c.port_offset for c in CHANNELS.values()) + 1


class InsecureBind(ValueError):
    """Binding beyond loopback without CURVE keys, and without --insecure."""


def is_loopback(host: str) -> bool:
    """True when `host` (an address, a name, or * / 0.0.0.0) reaches this machine only."""
    host = host.strip("[]")
    if host in ("*", "", "0.0.0.0", "::"):
        return False
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:  # a host name: loopback only if every address it resolves to is
        infos = pysocket.getaddrinfo(host, None)
    except OSError:
        return False  # an interface name (eth0) or an unknown name: assume it is exposed
    return bool(infos) and all(ipaddress.ip_address(i[4][0].split("%")[0]).is_loopback for i in infos)


def check_exposure(binds: dict[str, str], security: Security) -> None:
    """Refuse non-loopback binds without keys (unless --insecure); warn, naming the ports, when insecure.

    binds: channel name -> the tcp://HOST:PORT it binds.
    """
    if security.encrypted:
        return
    exposed = {}
    for name, endpoint in binds.items():
        host, port = parse_endpoint(endpoint)
        if not is_loopback(host) and f"{host}:{port}" not in security.warned:
            exposed[name] = f"{host}:{port}"
    if not exposed:
        return
    listing = ", ".join(f"{name} {where}" for name, where in exposed.items())
    if not security.insecure:
        raise InsecureBind(
            f"refusing to bind {listing} without encryption: anyone who reaches these ports could read the "
            f"run and push episodes. Make keys with higher-keys and pass --keys DIR, or bind 127.0.0.1, or "
            f"accept the risk with --insecure")
    log.warning("INSECURE (--insecure): %s bound without CURVE; any host that reaches these ports can read "
                "the config, the weights and the telemetry, and push episodes", listing)
    security.warned.update(exposed.values())  # said once per port, not again when each socket is opened


def check_binds(endpoints, bind_host: str | None, security: Security, binder: str | None = None) -> None:
    """check_exposure for every channel that `binder` binds (every channel when None), as bound on
    `bind_host`: all exposed ports are named in one refusal, before any socket exists."""
    check_exposure({name: bind_address(endpoints[name], bind_host) for name, channel in CHANNELS.items()
                    if binder in (None, channel.binder)}, security)


def open_channel(ctx: zmq.Context, name: str, side: Literal["bind", "connect"], endpoint: str,
                 security: Security, bind_host: str | None = None, identity: bytes | str | None = None
                 ) -> zmq.Socket:
    """A socket on channel `name`: bound (the channel's binder) or connected (one of its connectors).

    endpoint: the advertised tcp://HOST:PORT; a binder binds it on `bind_host` instead of HOST if given.
    Under keys the binder is a CURVE server whose context authenticates clients against the allow-list
    (admitting only keys whose roles include one of the channel's connectors), and a connector a CURVE
    client; without keys, a bind beyond loopback needs security.insecure.
    """
    channel = CHANNELS.get(name)
    if channel is None:
        raise ValueError(f"unknown channel {name!r}; the channels are {sorted(CHANNELS)}")
    if side == "bind":
        address = bind_address(endpoint, bind_host)
        check_exposure({name: address}, security)
        return sockets.make_socket(ctx, channel.bind_kind, bind=address, hwm=channel.bind_hwm,
                                   kernel_buffer_bytes=channel.kernel_buffer,
                                   curve=security.server(ctx, name, channel.connectors))
    if side == "connect":
        return sockets.make_socket(ctx, channel.connect_kind, connect=endpoint, hwm=channel.connect_hwm,
                                   kernel_buffer_bytes=channel.kernel_buffer, conflate=channel.conflate,
                                   linger_ms=channel.connect_linger_ms, identity=identity,
                                   curve=security.client())
    raise ValueError(f"side must be 'bind' or 'connect', got {side!r}")
