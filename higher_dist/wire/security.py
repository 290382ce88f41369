"""CURVE encryption and a client allow-list for runs that span hosts (off by default: loopback needs neither).

Key directory layout made by `generate_keys` (and read by everything else here):
    server.key / server.key_secret        the learner's (and relabeler's) server key pair
    <client>.key / <client>.key_secret    a client key pair per name: one per host or role (higher-keys
                                          --client NAME --role ROLES), or the one shared "client" pair
    allowed_clients/<client>.key          public keys the servers accept, with the roles each may take
                                          (the allow-list: wire/allowlist.py)
Secret files are created with mode 0600 whatever the umask (and an existing one is set back to 0600).
Copy server.key and a host's own client pair to that host; only the hosts of servers (learner,
relabeler) need server.key_secret and allowed_clients/.

A CURVE server without a ZAP handler encrypts but accepts any client key; `start_authenticator` installs
a ZAP handler (zmq's ThreadAuthenticator) on the server's context that admits a key only while it is in
allowed_clients/ (read again at every handshake) and only on the channels its roles connect to (each
server socket's ZAP domain is its channel's name). Each process with a CURVE server needs its own (a ZAP
handler serves one context): `Security.server(ctx, channel)` starts it on first use.

The authenticator answers with a user id (the client's public key) on the control channel only, where
the learner reads it from each message ("User-Id") to bind a hello to the roles of its key. Elsewhere it
answers with an empty user id, on purpose: with a user id, libzmq (4.3) puts a "credential" message into
each new connection's receive pipe; the pipe counts it as written but `pipe_t::read` skips it without
counting it as read, so it holds one slot of the high-water mark for the life of the connection. With
RCVHWM 1 (the experience channels) the pipe is then full before the first episode: poll says POLLIN (the
credential is there), recv says EAGAIN, and nothing ever arrives. (Control's queues hold 1000.)
"""
from __future__ import annotations

import logging
import os
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from zmq.utils import z85

from higher_dist.paths import ensure_folder
from higher_dist.wire.allowlist import REVOKED_DIR, AllowList, check_name, client_key_name, entry_text

log = logging.getLogger("higher_dist.security")
SERVER_NAME = "server"
ALLOWED_DIR = "allowed_clients"
USER_ID_DOMAIN = "control"  # the one channel whose messages carry the sender's key (see above)


def _write_key_file(path: Path, public: bytes, secret: bytes | None, metadata: str = "") -> None:
    """A key file in zmq.auth's format; a secret one is created 0600 (no window where others can read it)."""
    kind = "Secret" if secret is not None else "Public"
    lines = [f"#   ZeroMQ CURVE {kind} Certificate, written by higher-keys {time.strftime('%Y-%m-%d %H:%M:%S')}",
             "#   Keep secret files readable by their owner only." if secret is not None else "#",
             "", "metadata", *([metadata] if metadata else []), "curve",
             f'    public-key = "{public.decode("ascii")}"']
    if secret is not None:
        lines.append(f'    secret-key = "{secret.decode("ascii")}"')
    mode = 0o600
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)  # O_CREAT's mode is masked by the umask; fchmod is not
        os.write(fd, ("\n".join(lines) + "\n").encode("ascii"))
    finally:
        os.close(fd)
    os.replace(tmp, path)


def generate_keys(keys_dir: str | os.PathLike, clients: tuple[str, ...] = ("client",),
                  overwrite: bool = False, roles: frozenset[str] | None = None) -> dict[str, Path]:
    """Create the server pair, the client pairs and their allow-list entries; returns name -> public key path.

    `roles`: what the clients' keys may take (wire/allowlist.py); None writes no roles line (any role,
    the shared pair). Existing keys are kept unless `overwrite`, so rerunning the command never locks
    out deployed clients; their allow-list entry is written again with `roles`."""
    for name in clients:
        check_name(name)
        if (Path(keys_dir) / REVOKED_DIR / f"{name}.key").exists():
            raise ValueError(f"{name}: revoked ({Path(keys_dir) / REVOKED_DIR / name}.key); choose another name "
                             "for a new key, or move that file back to allowed_clients/ to lift the revocation")
    root = Path(keys_dir)
    allowed = root / ALLOWED_DIR
    ensure_folder(root, "keys folder")
    ensure_folder(allowed, "keys folder")
    # Private whatever the umask: who may join is decided by what is in these folders.
    os.chmod(root, 0o700)
    os.chmod(allowed, 0o700)
    publics = {}
    for name in (SERVER_NAME, *clients):
        public, secret_file = root / f"{name}.key", root / f"{name}.key_secret"
        if overwrite or not public.exists() or not secret_file.exists():
            public_key, secret_key = zmq.curve_keypair()
            _write_key_file(secret_file, public_key, secret_key)
            _write_key_file(public, public_key, None)
        else:
            os.chmod(secret_file, 0o600)  # written by an older version, or loosened by hand
        publics[name] = public
        if name != SERVER_NAME:
            key, _ = zmq.auth.load_certificate(str(public))
            _write_key_file(allowed / public.name, key, None, entry_text(key, roles))
    return publics


def load_public(path_or_key: str | bytes | os.PathLike) -> bytes:
    """A z85 public key given as the key itself (40 characters) or as a path to a .key file."""
    if isinstance(path_or_key, bytes) and len(path_or_key) == 40:
        return path_or_key
    if isinstance(path_or_key, str) and len(path_or_key) == 40 and not os.path.exists(path_or_key):
        return path_or_key.encode("ascii")
    public, _ = zmq.auth.load_certificate(str(path_or_key))
    return public


@dataclass(frozen=True)
class CurveServer:
    """Makes a socket a CURVE server with the key pair in keys_dir; pass as make_socket(curve=...)."""

    keys_dir: str
    domain: str = ""  # the ZAP domain: the channel's name, which the authenticator checks roles against

    def apply(self, socket: zmq.Socket) -> None:
        server_curve(socket, self.keys_dir)
        if self.domain:
            socket.zap_domain = self.domain.encode("ascii")


@dataclass(frozen=True)
class CurveClient:
    """Makes a socket a CURVE client; `server_public` is the server's key or key file (default keys_dir/server.key)."""

    keys_dir: str
    server_public: str | bytes | None = None
    name: str = "client"

    def apply(self, socket: zmq.Socket) -> None:
        client_curve(socket, self.keys_dir, self.server_public, self.name)


def _load_secret(path: Path) -> tuple[bytes, bytes]:
    if not path.exists():
        raise ValueError(f"--keys: {path} is missing (make keys with higher-keys and copy the pair here)")
    if path.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        log.warning("%s is readable by other users; chmod 600 it", path)
    public, secret = zmq.auth.load_certificate(str(path))
    if not secret:
        raise ValueError(f"--keys: {path} holds no secret key")
    return public, secret


def server_curve(socket: zmq.Socket, keys_dir: str | os.PathLike) -> None:
    """CURVE server options; must be set before bind."""
    public, secret = _load_secret(Path(keys_dir) / f"{SERVER_NAME}.key_secret")
    socket.curve_secretkey = secret
    socket.curve_publickey = public
    socket.curve_server = True


def client_curve(socket: zmq.Socket, keys_dir: str | os.PathLike, server_public: str | bytes | None = None,
                 name: str = "client") -> None:
    """CURVE client options; must be set before connect."""
    public, secret = _load_secret(Path(keys_dir) / f"{name}.key_secret")
    socket.curve_secretkey = secret
    socket.curve_publickey = public
    socket.curve_serverkey = load_public(server_public if server_public is not None
                                         else Path(keys_dir) / f"{SERVER_NAME}.key")


class RoleAuthenticator(ThreadAuthenticator):
    """Admits a CURVE key while it is in the allow-list (read at every handshake) and only on channels
    its roles connect to (`domains`: ZAP domain -> the roles that connect there); gives the key as the
    user id on the control channel only (see the module's docstring)."""

    def __init__(self, ctx: zmq.Context, folder: Path, domains: dict[str, tuple[str, ...]]):
        super().__init__(ctx)
        self.allow_list, self.domains = AllowList(folder, max_age_s=0.0), domains
        self._user_id = ""

    async def _authenticate_curve(self, domain: str, client_key: bytes) -> tuple[bool, bytes]:
        key = z85.encode(client_key)
        self._user_id = ""
        grant = self.allow_list.grant(key)
        if grant is None:
            return False, b"Unknown key"
        if not grant.may_connect(self.domains.get(domain, ())):
            log.warning("refused key %s (%s) on the %s channel: it may take %s", grant.name,
                        key.decode("ascii"), domain, grant.describe())
            return False, b"Role not allowed on this channel"
        if domain == USER_ID_DOMAIN:
            self._user_id = key.decode("ascii")
        return True, b"OK"

    def curve_user_id(self, client_public_key: bytes) -> str:
        return self._user_id  # set by _authenticate_curve just before, in the same step


def start_authenticator(ctx: zmq.Context, keys_dir: str | os.PathLike, allow_ips: tuple[str, ...] = (),
                        domains: dict[str, tuple[str, ...]] | None = None) -> RoleAuthenticator:
    """Enforce the allow-list (and optionally client IPs) for every CURVE server socket of `ctx`.

    `domains` (ZAP domain -> connecting roles) may grow after the start. Call before binding; call
    `.stop()` on the result at shutdown.
    """
    allowed = Path(keys_dir) / ALLOWED_DIR
    if not allowed.is_dir() or not any(allowed.glob("*.key")):
        raise ValueError(f"--keys: {allowed} holds no client keys, so no client could connect")
    auth = RoleAuthenticator(ctx, allowed, {} if domains is None else domains)
    auth.start()
    if allow_ips:
        auth.allow(*allow_ips)
    auth.configure_curve(domain="*", location=str(allowed))  # CURVE on; the keys are checked above
    return auth


@dataclass
class Security:
    """How a process secures its sockets: CURVE with the keys in `keys`, or nothing (loopback, or
    beyond it only with `insecure`). Binders get `server(ctx)`, connectors `client()`; `close()` stops
    the authenticators it started."""

    keys: str | None = None
    insecure: bool = False
    client_name: str | None = None  # the client pair (--key); None: allowlist.client_key_name's choice
    role: str = "client"  # the role this process connects as, which that choice looks for
    warned: set[str] = field(default_factory=set, repr=False)  # HOST:PORT already warned about (--insecure)
    _auths: dict[int, ThreadAuthenticator] = field(default_factory=dict, repr=False)

    @property
    def encrypted(self) -> bool:
        return self.keys is not None

    def server(self, ctx: zmq.Context, channel: str = "", connectors: tuple[str, ...] = ()) -> CurveServer | None:
        """CURVE server options for a socket of `channel`, which the roles `connectors` connect to."""
        if self.keys is None:
            return None
        if id(ctx) not in self._auths:  # one ZAP handler per context, before its first CURVE bind
            self._auths[id(ctx)] = start_authenticator(ctx, self.keys)
        if channel:
            self._auths[id(ctx)].domains[channel] = connectors
        return CurveServer(self.keys, domain=channel)

    def client(self) -> CurveClient | None:
        if self.keys is None:
            return None
        return CurveClient(self.keys, name=client_key_name(self.keys, self.role, self.client_name))

    def allow_list(self) -> AllowList | None:
        """The allow-list as the control channel reads it (again at most once a second); None without keys."""
        return AllowList(Path(self.keys) / ALLOWED_DIR) if self.keys is not None else None

    def close(self) -> None:
        for auth in self._auths.values():
            auth.stop()
        self._auths.clear()
