"""The only place that knows the cluster's endpoints.

Every socket of the system is one of these five, laid out from one base port:

    control     = base      learner ROUTER: hello/welcome, register, heartbeats, stats, stop
    experience  = base + 1  learner PULL:   episodes (originals and relabelled copies) from the relabeler
    weights     = base + 2  learner PUB:    versioned Q-network weights, one frame, for actors (CONFLATE)
    telemetry   = base + 3  learner PUB:    one msgpack record per refresh, for dashboards
    relabeler   = base + 4  relabeler PULL: episodes from actors

An actor or a dashboard needs only the learner's control address; everything else is derived here or
sent in the welcome message.
"""
from __future__ import annotations

import re
import socket
from dataclasses import asdict, dataclass

DEFAULT_HOST = "127.0.0.1"  # loopback only unless the user asks for more
DEFAULT_BASE_PORT = 5555
# The experience path (actor -> relabeler -> learner) holds little in flight, so the learner's rate
# limiter reaches the actors within a few batches and the replay never trains on stale experience.
EXPERIENCE_HWM = 1  # messages (episode batches) per socket queue
EXPERIENCE_BUFFER = 64 << 10  # bytes of kernel socket buffer
_ENDPOINT = re.compile(r"^tcp://(?P<host>[^:/\s]+|\[[0-9a-fA-F:]+\]):(?P<port>\d{1,5})$")


@dataclass(frozen=True)
class Endpoints:
    control: str
    experience: str
    weights: str
    telemetry: str
    relabeler: str

    @classmethod
    def from_base(cls, host: str = DEFAULT_HOST, base_port: int = DEFAULT_BASE_PORT) -> "Endpoints":
        if not 1024 <= base_port <= 65535 - 4:
            raise ValueError(f"base port must be in [1024, 65531], got {base_port}")
        return cls(*(f"tcp://{host}:{base_port + i}" for i in range(5)))

    @classmethod
    def from_control(cls, control: str) -> "Endpoints":
        host, port = parse_endpoint(control)
        return cls.from_base(host, port)

    def as_dict(self) -> dict[str, str]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Endpoints":
        missing = {"control", "experience", "weights", "telemetry", "relabeler"} - set(d)
        if missing:
            raise ValueError(f"endpoints: missing {sorted(missing)}")
        for v in d.values():
            parse_endpoint(v)
        return cls(d["control"], d["experience"], d["weights"], d["telemetry"], d["relabeler"])


def parse_endpoint(endpoint: str) -> tuple[str, int]:
    """('host', port) of a tcp://host:port endpoint, or a ValueError that says what is wrong."""
    m = _ENDPOINT.match(endpoint or "")
    if not m:
        raise ValueError(f"endpoint {endpoint!r} is not of the form tcp://HOST:PORT")
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise ValueError(f"endpoint {endpoint!r}: port out of range")
    return m["host"], port


def bind_address(endpoint: str, bind_host: str | None = None) -> str:
    """The address a role binds for an advertised endpoint (optionally on another interface, e.g. *)."""
    host, port = parse_endpoint(endpoint)
    return f"tcp://{bind_host or host}:{port}"


def free_base_port(host: str = DEFAULT_HOST, span: int = 5, tries: int = 200) -> int:
    """A base port whose `span` successive ports are free now (tests and parallel local clusters)."""
    import random

    for _ in range(tries):
        base = random.randint(20_000, 60_000)
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
            raise ValueError(f"{name} port {port} on {bind_host or host} is in use ({e.strerror}): is another "
                             f"cluster running? Stop it or pick other ports with --port-base") from None
        finally:
            s.close()

