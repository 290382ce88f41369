"""CURVE encryption and a client allow-list for runs that span hosts (off by default: loopback needs neither).

Key directory layout made by `generate_keys` (and read by everything else here):
    server.key / server.key_secret        the learner's (and relabeler's) server key pair
    <client>.key / <client>.key_secret    a client key pair per name (default: one "client" pair)
    allowed_clients/<client>.key          public keys the servers accept (the allow-list)
Secret files are written by zmq.auth with mode 0600. Copy server.key and one client pair to a client host;
only the head needs server.key_secret and allowed_clients/.

A CURVE server without a ZAP handler encrypts but accepts any client key; `start_authenticator` installs
zmq's ThreadAuthenticator on the server's context, which refuses keys missing from allowed_clients/.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

SERVER_NAME = "server"
ALLOWED_DIR = "allowed_clients"


def generate_keys(keys_dir: str | os.PathLike, clients: tuple[str, ...] = ("client",),
                  overwrite: bool = False) -> dict[str, Path]:
    """Create the server pair, the client pairs and the allow-list; returns name -> public key path.

    Existing keys are kept unless `overwrite`, so rerunning the command never locks out deployed clients.
    """
    root = Path(keys_dir)
    allowed = root / ALLOWED_DIR
    allowed.mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o700)
    publics = {}
    for name in (SERVER_NAME, *clients):
        public = root / f"{name}.key"
        if overwrite or not public.exists():
            public_file, _ = zmq.auth.create_certificates(str(root), name)
            public = Path(public_file)
        publics[name] = public
        if name != SERVER_NAME:
            shutil.copyfile(public, allowed / public.name)
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


def server_curve(socket: zmq.Socket, keys_dir: str | os.PathLike) -> None:
    """CURVE server options; must be set before bind."""
    public, secret = zmq.auth.load_certificate(str(Path(keys_dir) / f"{SERVER_NAME}.key_secret"))
    socket.curve_secretkey = secret
    socket.curve_publickey = public
    socket.curve_server = True


def client_curve(socket: zmq.Socket, keys_dir: str | os.PathLike, server_public: str | bytes | None = None,
                 name: str = "client") -> None:
    """CURVE client options; must be set before connect."""
    public, secret = zmq.auth.load_certificate(str(Path(keys_dir) / f"{name}.key_secret"))
    socket.curve_secretkey = secret
    socket.curve_publickey = public
    socket.curve_serverkey = load_public(server_public if server_public is not None
                                         else Path(keys_dir) / f"{SERVER_NAME}.key")


def start_authenticator(ctx: zmq.Context, keys_dir: str | os.PathLike,
                        allow_ips: tuple[str, ...] = ()) -> ThreadAuthenticator:
    """Enforce the allow-list (and optionally client IPs) for every CURVE server socket of `ctx`.

    Call before binding; call `.stop()` on the result at shutdown.
    """
    auth = ThreadAuthenticator(ctx)
    auth.start()
    if allow_ips:
        auth.allow(*allow_ips)
    auth.configure_curve(domain="*", location=str(Path(keys_dir) / ALLOWED_DIR))
    return auth
