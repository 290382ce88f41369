"""The only place that knows the cluster's endpoints: one per channel of launch/channels.py, laid out from
one base port by the channels' port offsets (control = base, experience = base+1, weights = base+2,
telemetry = base+3, episodes = base+4).

An actor or a dashboard needs only the learner's control address; everything else is derived here or
sent in the welcome message (which carries the relabeler's registered address for `episodes`).
"""
from __future__ import annotations

import errno
import fcntl
import socket
import tempfile
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from higher_dist.launch.addresses import bind_address, parse_endpoint  # noqa: F401 - part of this module's API
from higher_dist.launch.channels import CHANNELS, PORT_SPAN

DEFAULT_HOST = "127.0.0.1"  # loopback only unless the user asks for more
DEFAULT_BASE_PORT = 5555


@dataclass(frozen=True)
class Endpoints:
    """tcp://HOST:PORT of each channel, by channel name."""

    control: str
    experience: str
    weights: str
    telemetry: str
    episodes: str

    @classmethod
    def from_base(cls, host: str = DEFAULT_HOST, base_port: int = DEFAULT_BASE_PORT) -> "Endpoints":
        if not 1024 <= base_port <= 65536 - PORT_SPAN:
            raise ValueError(f"base port must be in [1024, {65536 - PORT_SPAN}], got {base_port}")
        return cls(**{f.name: f"tcp://{host}:{base_port + CHANNELS[f.name].port_offset}" for f in fields(cls)})

    @classmethod
    def from_control(cls, control: str) -> "Endpoints":
        host, port = parse_endpoint(control)
        return cls.from_base(host, port)

    def __getitem__(self, channel: str) -> str:
        if channel not in CHANNELS:
            raise KeyError(f"no channel {channel!r}")
        return getattr(self, channel)

    def with_endpoint(self, channel: str, endpoint: str) -> "Endpoints":
        parse_endpoint(endpoint)
        return replace(self, **{channel: endpoint})

    def as_dict(self) -> dict[str, str]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Endpoints":
        missing = {f.name for f in fields(cls)} - set(d)
        if missing:
            raise ValueError(f"endpoints: missing {sorted(missing)}")
        for name in (f.name for f in fields(cls)):
            parse_endpoint(d[name])
        return cls(**{f.name: d[f.name] for f in fields(cls)})


# Bases are drawn below the ephemeral ports the OS gives outgoing connections (Linux: from 32768; macOS and
# Windows: from 49152): a port found free there can be taken by another local cluster's connect() before
# this one's role binds it, and the bind then fails on every restart.
FREE_PORTS = (20_000, 32_000)


def free_base_port(host: str = DEFAULT_HOST, span: int = PORT_SPAN, tries: int = 200) -> int:
    """A base port whose `span` successive ports are free now (tests and parallel local clusters)."""
    import random

    for _ in range(tries):
        base = random.randint(FREE_PORTS[0], FREE_PORTS[1] - span)
        socks = []
        try:
            for i in range(span):
                s = socket.socket()
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((host, base + i))
                socks.append(s)
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError("no free port range found")


def claim_ports(endpoints: "Endpoints", bind_host: str | None = None) -> list:
    """Claim the cluster's ports on this machine for as long as the returned files stay open (a launcher
    keeps them for its life; the OS drops the claims when it exits, however it exits).

    check_free alone has a race: two launchers started at the same instant both find the ports free,
    since neither learner has bound them yet, and the loser's learner then fails in a restart loop. An
    exclusive flock per port (a lock file in the temp folder) closes it for launchers on one machine.
    """
    folder = Path(tempfile.gettempdir()) / "higher-dist-ports"
    folder.mkdir(exist_ok=True)
    held = []
    for name, endpoint in sorted(endpoints.as_dict().items(), key=lambda kv: parse_endpoint(kv[1])[1]):
        host, port = parse_endpoint(endpoint)
        f = open(folder / f"{bind_host or host}-{port}.lock", "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            for other in held:
                other.close()
            raise ValueError(f"{name} port {port} on {bind_host or host} is claimed by another higher-cluster "
                             "starting on this machine: pick other ports with --port-base") from None
        held.append(f)
    return held


def check_free(endpoints: "Endpoints", bind_host: str | None = None) -> None:
    """Refuse, with a message that says what to do, to start on ports that something already holds.

    SO_REUSEADDR, as libzmq's own listeners use: a port whose last connections sit in TIME_WAIT (a run
    that just ended) is free to bind, so runs can follow one another; a port something listens on is not.
    """
    for name, endpoint in endpoints.as_dict().items():
        host, port = parse_endpoint(endpoint)
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((bind_host or host, port))
        except OSError as e:
            if e.errno == errno.EADDRNOTAVAIL:
                raise ValueError(f"{bind_host or host} is not an address of this host ({e.strerror}): give "
                                 "--host (or --bind-host) one of its own addresses") from None
            raise ValueError(f"{name} port {port} on {bind_host or host} is in use ({e.strerror}): is another "
                             f"cluster running? Stop it or pick other ports with --port-base") from None
        finally:
            s.close()

