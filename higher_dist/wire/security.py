"""CURVE encryption and a client allow-list for runs that span hosts (off by default: loopback needs neither).

Key directory layout made by `generate_keys` (and read by everything else here):
    server.key / server.key_secret        the learner's (and relabeler's) server key pair
    <client>.key / <client>.key_secret    a client key pair per name (default: one "client" pair)
    allowed_clients/<client>.key          public keys the servers accept (the allow-list)
Secret files are created with mode 0600 whatever the umask (and an existing one is set back to 0600).
Copy server.key and one client pair to a client host; only the hosts of servers (learner, relabeler) need
server.key_secret and allowed_clients/.

A CURVE server without a ZAP handler encrypts but accepts any client key; `start_authenticator` installs
zmq's ThreadAuthenticator on the server's context, which refuses keys missing from allowed_clients/. Each
process with a CURVE server needs its own (a ZAP handler serves one context): `Security.server(ctx)` starts
it on first use.

The authenticator answers with an empty user id, on purpose. With a user id, libzmq (4.3) puts a
"credential" message into each new connection's receive pipe; the pipe counts it as written but
`pipe_t::read` skips it without counting it as read, so it holds one slot of the high-water mark for the
life of the connection. With RCVHWM 1 (the experience channels) the pipe is then full before the first
episode: poll says POLLIN (the credential is there), recv says EAGAIN, and nothing ever arrives.
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

from higher_dist.paths import ensure_folder

log = logging.getLogger("higher_dist.security")
SERVER_NAME = "server"
ALLOWED_DIR = "allowed_clients"


def _write_key_file(path: Path, public: bytes, secret: bytes | None) -> None:
    """A key file in zmq.auth's format; a secret one is created 0600 (no window where others can read it)."""
    kind = "Secret" if secret is not None else "Public"
    lines = [f"#   ZeroMQ CURVE {kind} Certificate, written by higher-keys {time.strftime('%Y-%m-%d %H:%M:%S')}",
             "#   Keep secret files readable by their owner only." if secret is not None else "#",
             "", "metadata", "curve", f'    public-key = "{public.decode("ascii")}"']
    if secret is not None:
        lines.append(f'    secret-key = "{secret.decode("ascii")}"')
    mode = 0o600 if secret is not None else 0o644
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)  # O_CREAT's mode is masked by the umask; fchmod is not
        os.write(fd, ("\n".join(lines) + "\n").encode("ascii"))
    finally:
        os.close(fd)
    os.replace(tmp, path)


def generate_keys(keys_dir: str | os.PathLike, clients: tuple[str, ...] = ("client",),
                  overwrite: bool = False) -> dict[str, Path]:
    """Create the server pair, the client pairs and the allow-list; returns name -> public key path.

    Existing keys are kept unless `overwrite`, so rerunning the command never locks out deployed clients.
    """
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
            _write_key_file(allowed / public.name, key, None)
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

    def apply(self, socket: zmq.Socket) -> None:
        server_curve(socket, self.keys_dir)


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


def start_authenticator(ctx: zmq.Context, keys_dir: str | os.PathLike,
                        allow_ips: tuple[str, ...] = ()) -> ThreadAuthenticator:
    """Enforce the allow-list (and optionally client IPs) for every CURVE server socket of `ctx`.

    Call before binding; call `.stop()` on the result at shutdown.
    """
    allowed = Path(keys_dir) / ALLOWED_DIR
    if not allowed.is_dir() or not any(allowed.glob("*.key")):
        raise ValueError(f"--keys: {allowed} holds no client keys, so no client could connect")
    auth = ThreadAuthenticator(ctx)
    # No user id in the reply: see the module's docstring (it would take a slot of every queue).
    auth.curve_user_id = lambda _client_key: ""
    auth.start()
    if allow_ips:
        auth.allow(*allow_ips)
    auth.configure_curve(domain="*", location=str(Path(keys_dir) / ALLOWED_DIR))
    return auth


@dataclass
class Security:
    """How a process secures its sockets: CURVE with the keys in `keys`, or nothing (loopback, or
    beyond it only with `insecure`). Binders get `server(ctx)`, connectors `client()`; `close()` stops
    the authenticators it started."""

    keys: str | None = None
    insecure: bool = False
    client_name: str = "client"
    warned: set[str] = field(default_factory=set, repr=False)  # HOST:PORT already warned about (--insecure)
    _auths: dict[int, ThreadAuthenticator] = field(default_factory=dict, repr=False)

    @property
    def encrypted(self) -> bool:
        return self.keys is not None

    def server(self, ctx: zmq.Context) -> CurveServer | None:
        if self.keys is None:
            return None
        if id(ctx) not in self._auths:  # one ZAP handler per context, before its first CURVE bind
            self._auths[id(ctx)] = start_authenticator(ctx, self.keys)
        return CurveServer(self.keys)

    def client(self) -> CurveClient | None:
        return CurveClient(self.keys, name=self.client_name) if self.keys is not None else None

    def close(self) -> None:
        for auth in self._auths.values():
            auth.stop()
        self._auths.clear()
