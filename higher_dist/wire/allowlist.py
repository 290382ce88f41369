"""The allow-list: which client keys may join a run under --keys, and as which roles.

`KEYS/allowed_clients/NAME.key` is one entry: a public key (zmq's certificate format) named after the
host or role that holds its secret, with the roles it may take in its metadata (`roles = "actor"`). An
entry without a roles line (the single shared `client` pair of older key folders) may take any role.

Roles are enforced twice. At the CURVE handshake (the ZAP handler, security.start_authenticator), a key
reaches only the channels its roles connect to (launch/channels.py): an actor's key cannot push episodes
into the learner's replay, nor a relabeler's read the weights; every listed key may read telemetry (a
dashboard). On the control channel the learner reads each message's key and refuses a hello, or a
`register` of the relabeler's address, for a role that key may not take (roles/control_server.py).

The folder is read again for every handshake and at most once a second on the control channel, so an
entry deleted (or moved out) is revoked without a restart: see docs/multi-host.md.
"""
from __future__ import annotations

import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import zmq.auth

log = logging.getLogger("higher_dist.security")
ROLES = ("actor", "relabeler")  # the roles a key may be granted; "any" grants them all
ANY = "any"
REVOKED_DIR = "revoked"  # where a revoked entry is moved: higher-keys will not list that name again
OPEN_TO_EVERY_KEY = "dashboard"  # a channel a dashboard connects to admits every listed key (telemetry)
_ROLES_LINE = re.compile(r'^\s*roles\s*=\s*"([^"]*)"\s*$', re.MULTILINE)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def check_name(name: str) -> str:
    """A key pair's name (a host or a role): it becomes a file name, so letters, digits, - _ . only."""
    if not _NAME.match(name) or name.endswith((".key", ".key_secret")) or name == "server":
        raise ValueError(f"key name {name!r}: use letters, digits, '-', '_' and '.' (up to 64), not 'server'")
    return name


def parse_roles(text: str) -> frozenset[str]:
    """'actor', 'relabeler', 'actor,relabeler' or 'any' -> the roles granted; ValueError otherwise."""
    parts = {p.strip() for p in text.split(",") if p.strip()}
    if ANY in parts:
        return frozenset(ROLES)
    unknown = parts - set(ROLES)
    if unknown or not parts:
        raise ValueError(f"roles {text!r}: give {', '.join(ROLES)}, a comma-separated list of them, or {ANY}")
    return frozenset(parts)


@dataclass(frozen=True)
class Grant:
    """One allow-list entry: the key's name (its file name) and the roles it may take."""

    name: str
    roles: frozenset[str]

    def may(self, role: str) -> bool:
        return role in self.roles or role == OPEN_TO_EVERY_KEY

    def may_connect(self, connectors: tuple[str, ...]) -> bool:
        """Whether this key may complete a handshake on a channel these roles connect to."""
        return not connectors or any(self.may(role) for role in connectors)

    def describe(self) -> str:
        return ", ".join(sorted(self.roles))


def entry_text(public: bytes, roles: frozenset[str] | None) -> str:
    """The metadata lines of an allow-list entry (none for a key that may take any role)."""
    if roles is None or roles == frozenset(ROLES):
        return f'    roles = "{ANY}"' if roles is not None else ""
    return f'    roles = "{",".join(sorted(roles))}"'


def read_allow_list(folder: str | os.PathLike) -> dict[bytes, Grant]:
    """z85 public key -> Grant for every readable entry of the folder; an unreadable one is skipped
    with a warning (it admits nobody), never fatal."""
    grants: dict[bytes, Grant] = {}
    for path in sorted(Path(folder).glob("*.key")):
        try:
            public, _ = zmq.auth.load_certificate(str(path))
            found = _ROLES_LINE.search(path.read_text(errors="replace"))
            roles = parse_roles(found.group(1)) if found else frozenset(ROLES)
        except (OSError, ValueError) as e:
            log.warning("allow-list entry %s skipped: %s", path, e)
            continue
        grants[public] = Grant(path.name[:-len(".key")], roles)
    return grants


class AllowList:
    """The allow-list folder, read again when the copy in hand is older than `max_age_s` (0: always)."""

    def __init__(self, folder: str | os.PathLike, max_age_s: float = 1.0):
        self.folder, self.max_age_s = Path(folder), max_age_s
        self._grants: dict[bytes, Grant] = {}
        self._read_at = -float("inf")

    def grant(self, z85_key: bytes | str | None) -> Grant | None:
        """The entry of this public key, or None when it is not (or no longer) listed."""
        if not z85_key:
            return None
        now = time.monotonic()
        if now - self._read_at >= self.max_age_s:
            self._grants, self._read_at = read_allow_list(self.folder), now
        key = z85_key.encode("ascii") if isinstance(z85_key, str) else z85_key
        return self._grants.get(key)


def client_key_name(keys_dir: str | os.PathLike, role: str, explicit: str | None = None) -> str:
    """Which client pair in keys_dir a role uses: `explicit` (--key), else the pair named after the
    role, else the shared `client` pair, else the folder's only pair (any pair for a dashboard);
    refused by name otherwise."""
    root = Path(keys_dir)
    if explicit is not None:
        return check_name(explicit)
    pairs = sorted(p.name[:-len(".key_secret")] for p in root.glob("*.key_secret")
                   if p.name != "server.key_secret")
    # Any listed key may read telemetry, so a dashboard takes whichever pair is there.
    anyone = pairs if len(pairs) == 1 or role == OPEN_TO_EVERY_KEY else ()
    for name in (role, "client", *anyone):
        if name in pairs:
            return name
    if not pairs:
        raise ValueError(f"--keys {keys_dir}: no client key pair (NAME.key_secret) there; make one with "
                         f"higher-keys DIR --client NAME --role {role if role in ROLES else 'ROLES'} and copy it here")
    raise ValueError(f"--keys {keys_dir}: several client key pairs ({', '.join(pairs)}) and none named "
                     f"{role!r} or 'client'; choose one with --key NAME")
