"""The one place that creates sockets and sets their options, and the send/receive helpers every role uses.

Receiving never raises on a bad message: `recv_message` drops it, counts it by reason in a `RejectCounter`
and logs it (rate-limited), because the design says one corrupt or hostile peer must not stop a role.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Mapping, Optional, Sequence

import zmq

from higher_dist.wire.codec import Message, WireError, decode, weights_of
from higher_dist.wire.schema import MAX_FRAME_BYTES

log = logging.getLogger("higher_dist.wire")

DEFAULT_HWM = 100  # messages; an episodes message is a batch, so 100 already buffers thousands of episodes
RECONNECT_IVL_MS = 100
RECONNECT_IVL_MAX_MS = 5000  # exponential backoff up to this while a peer is down


def make_socket(ctx: zmq.Context, kind: int, *, bind: str | Sequence[str] | None = None,
                connect: str | Sequence[str] | None = None, hwm: int = DEFAULT_HWM, linger_ms: int = 200,
                conflate: bool = False, identity: bytes | str | None = None, curve: Any = None,
                subscribe: bytes | None = b"", immediate: bool | None = None,
                max_msg_bytes: int = MAX_FRAME_BYTES, kernel_buffer_bytes: int | None = None) -> zmq.Socket:
    """A socket with the project's options set, then bound and/or connected.

    curve: an object with `apply(socket)` (security.CurveServer / CurveClient), applied before bind/connect.
    conflate: keep only the newest message (weights SUB); works with one-frame messages only.
    immediate: queue only to completed connections, so a PUSH blocks (backpressure) instead of piling
        messages onto a peer that is not there; default on for connecting PUSH sockets.
    subscribe: the SUB topic prefix (b"" = everything); ignored by other kinds.
    kernel_buffer_bytes: SO_SNDBUF/SO_RCVBUF, for the experience path where backpressure must be prompt.
    """
    sock = ctx.socket(kind)
    try:
        sock.setsockopt(zmq.LINGER, linger_ms)
        sock.setsockopt(zmq.SNDHWM, hwm)
        sock.setsockopt(zmq.RCVHWM, hwm)
        sock.setsockopt(zmq.RECONNECT_IVL, RECONNECT_IVL_MS)
        sock.setsockopt(zmq.RECONNECT_IVL_MAX, RECONNECT_IVL_MAX_MS)
        # No ZMTP heartbeats (HEARTBEAT_IVL): with them, libzmq 4.3 aborted the learner with
        # "Assertion failed: !_io_error (stream_engine_base.cpp:310)" when a peer died mid-run. Liveness
        # is the application's heartbeat messages instead (roles.registry marks silent roles dead).
        # libzmq drops an over-size frame and the connection before it is ever buffered in Python.
        sock.setsockopt(zmq.MAXMSGSIZE, max_msg_bytes)
        if kernel_buffer_bytes is not None:
            # Bound what the kernel buffers too: on loopback TCP buffers hold megabytes, i.e. tens of
            # thousands of frames of stale experience that high-water marks alone do not see.
            sock.setsockopt(zmq.SNDBUF, kernel_buffer_bytes)
            sock.setsockopt(zmq.RCVBUF, kernel_buffer_bytes)
        if conflate:
            sock.setsockopt(zmq.CONFLATE, 1)
        if immediate is None:
            immediate = kind == zmq.PUSH and connect is not None
        if immediate:
            sock.setsockopt(zmq.IMMEDIATE, 1)
        if identity is not None:
            sock.setsockopt(zmq.ROUTING_ID, identity.encode() if isinstance(identity, str) else identity)
        if kind == zmq.SUB and subscribe is not None:
            sock.setsockopt(zmq.SUBSCRIBE, subscribe)
        if curve is not None:
            curve.apply(sock)
        for endpoint in _endpoints(bind):
            sock.bind(endpoint)
        for endpoint in _endpoints(connect):
            sock.connect(endpoint)
    except Exception:
        sock.close(linger=0)
        raise
    return sock


def _endpoints(value: str | Sequence[str] | None) -> list[str]:
    if value is None:
        return []
    return [value] if isinstance(value, str) else list(value)


def bind_random(socket: zmq.Socket, host: str = "127.0.0.1") -> str:
    """Bind to a free TCP port on `host` and return the endpoint to connect to (tests, local clusters)."""
    port = socket.bind_to_random_port(f"tcp://{host}")
    return f"tcp://{host}:{port}"


class RejectCounter:
    """Counts dropped messages by reason and logs them at most once per `log_every_s` per reason."""

    def __init__(self, log_every_s: float = 10.0, logger: logging.Logger | None = None):
        self.log_every_s = log_every_s
        self.logger = logger or log
        self._counts: dict[str, int] = {}
        self._last_log: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()  # roles may receive on more than one thread

    def add(self, reason: str, detail: str = "", where: str = "") -> None:
        now = time.monotonic()
        with self._lock:
            self._counts[reason] = self._counts.get(reason, 0) + 1
            if now - self._last_log.get(reason, -1e18) < self.log_every_s:
                self._suppressed[reason] = self._suppressed.get(reason, 0) + 1
                return
            suppressed = self._suppressed.pop(reason, 0)
            self._last_log[reason] = now
        more = f" (+{suppressed} more since the last report)" if suppressed else ""
        self.logger.warning("dropped invalid message%s: %s %s%s", f" on {where}" if where else "", reason,
                            detail, more)

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())


REJECTS = RejectCounter()  # the process-wide default; roles report REJECTS.counts() in their stats


def send(socket: zmq.Socket, frames: Sequence[Any], flags: int = 0) -> bool:
    """Send encoded frames; False (not an exception) when a non-blocking send meets a full queue."""
    try:
        socket.send_multipart(frames, flags=flags, copy=False)
        return True
    except zmq.Again:
        return False


def send_routed(socket: zmq.Socket, identity: bytes, frames: Sequence[Any], flags: int = 0) -> bool:
    """ROUTER -> DEALER: the peer's identity frame, then the message."""
    return send(socket, [identity, *frames], flags)


def _recv_frames(socket: zmq.Socket, timeout_ms: int) -> list[zmq.Frame] | None:
    if timeout_ms >= 0 and not socket.poll(timeout_ms, zmq.POLLIN):
        return None
    try:
        return socket.recv_multipart(flags=zmq.NOBLOCK, copy=False)
    except zmq.Again:
        return None


# Called with the WireError and the peer's identity (ROUTER) or None. Lets a role react to a specific
# rejection, e.g. the learner answering a hello of another protocol version with `refuse`, or an actor
# stopping with a clear error when the learner's reply is in a version it cannot read.
OnReject = Callable[[WireError, Optional[bytes]], None]


def _decode_or_count(frames: Sequence[Any], counter: RejectCounter, where: str, on_reject: OnReject | None,
                     identity: bytes | None = None) -> Message | None:
    try:
        return decode(frames)
    except WireError as exc:
        counter.add(exc.reason, exc.detail, where)
        if on_reject is not None:
            on_reject(exc, identity)
    except Exception as exc:  # a decoder bug must not kill a role either; count it loudly
        counter.add("internal", f"{type(exc).__name__}: {exc}", where)
    return None


def recv_message(socket: zmq.Socket, timeout_ms: int = 0, counter: RejectCounter | None = None,
                 where: str = "", on_reject: OnReject | None = None) -> Message | None:
    """The next valid message, or None on timeout or when the message was invalid (counted, logged).

    timeout_ms: 0 polls without blocking, -1 waits forever.
    """
    frames = _recv_frames(socket, timeout_ms)
    if frames is None:
        return None
    return _decode_or_count(frames, counter or REJECTS, where, on_reject)


def recv_routed(socket: zmq.Socket, timeout_ms: int = 0, counter: RejectCounter | None = None,
                where: str = "", on_reject: OnReject | None = None) -> tuple[bytes, Message] | None:
    """ROUTER side: (peer identity, message), or None as recv_message."""
    routed = recv_routed_from(socket, timeout_ms, counter, where, on_reject)
    return None if routed is None else routed[:2]


def recv_routed_from(socket: zmq.Socket, timeout_ms: int = 0, counter: RejectCounter | None = None,
                     where: str = "", on_reject: OnReject | None = None) -> tuple[bytes, Message, str] | None:
    """As recv_routed, plus the sender's user id: the public key its CURVE handshake proved, where the
    channel's authenticator gives one (wire/security.py), else ""."""
    frames = _recv_frames(socket, timeout_ms)
    if frames is None:
        return None
    if len(frames) < 2:
        (counter or REJECTS).add("frame_count", "routed message without identity or body", where)
        return None
    identity = frames[0].bytes
    msg = _decode_or_count(frames[1:], counter or REJECTS, where, on_reject, identity)
    if msg is None:
        return None
    try:
        user_id = frames[1].get("User-Id") or ""
    except zmq.ZMQError:  # no user id on this connection (no keys)
        user_id = ""
    return identity, msg, user_id


def recv_weights(socket: zmq.Socket, expected: Mapping[str, Sequence[int]] | None = None, timeout_ms: int = 0,
                 counter: RejectCounter | None = None, where: str = "weights"
                 ) -> tuple[int, dict[str, Any]] | None:
    """(version, arrays) of the newest weights on a CONFLATE SUB socket, or None (nothing new, or invalid).

    The arrays are writable copies, as from codec.decode_weights.
    """
    msg = recv_message(socket, timeout_ms, counter, where)
    if msg is None:
        return None
    try:
        return weights_of(msg, expected)
    except WireError as exc:
        (counter or REJECTS).add(exc.reason, exc.detail, where)
        return None


class PendingSend:
    """At most one encoded message waiting for room on a (PUSH) socket whose peer pushes back.

    A full socket is the learner holding its replay ratio: the sender keeps the one message, waits a
    little for room (POLLOUT) instead of spinning, and produces nothing new until it has left, so
    nothing queues without bound in the sender either.
    """

    def __init__(self, socket: zmq.Socket):
        self.socket = socket
        self.frames: Sequence[Any] | None = None

    @property
    def busy(self) -> bool:
        return self.frames is not None

    def put(self, frames: Sequence[Any]) -> None:
        if self.frames is not None:
            raise RuntimeError("PendingSend.put: the previous message has not left yet")
        self.frames = frames

    def flush(self, wait_ms: int) -> bool:
        """Try to send the waiting message, waiting up to `wait_ms` for room; True once nothing waits."""
        if self.frames is None:
            return True
        if self.socket.poll(wait_ms, zmq.POLLOUT):
            try:
                self.socket.send_multipart(self.frames, flags=zmq.NOBLOCK, copy=False)
                self.frames = None
            except zmq.Again:
                pass
        return self.frames is None
