"""Endpoint text: tcp://HOST:PORT parsed and checked, and the address a binder binds for it. Below both
channels.py (which binds) and topology.py (which lays endpoints out), so neither imports the other."""
from __future__ import annotations

import re

_ENDPOINT = re.compile(r"^tcp://(?P<host>[^:/\s]+|\[[0-9a-fA-F:]+\]):(?P<port>\d{1,5})$")


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
