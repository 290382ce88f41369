"""The live dashboard: subscribe to the learner's telemetry and redraw with rich.

The learner PUBlishes one `telemetry` message (wire/schema.py; one frame, checked by the codec like any
other message) per record, several times a second. The dashboard only ever wants the newest one, so the
SUB socket is CONFLATEd with a tiny high-water mark: a slow terminal can never make messages pile up
anywhere. A frame that does not decode to a telemetry message is counted and ignored; a `stop` message
ends the dashboard (the learner sends it on shutdown).

Endpoints: a dashboard needs only the learner's control endpoint; `Endpoints.from_control` in
launch/topology.py (the only place that knows the port layout) gives the telemetry channel's. Under --keys
the telemetry is encrypted like every channel and the dashboard connects with a client key pair.
"""
from __future__ import annotations

import time
from typing import Any

import zmq
from rich.console import Console
from rich.live import Live

from higher_dist.launch.channels import open_channel
from higher_dist.roles.dashboard_view import DashboardState, render
from higher_dist.wire import codec
from higher_dist.wire.security import Security

MAX_FRAME_BYTES = 8 << 20  # a telemetry record is a few kB; refuse to buffer anything absurd


STOP = {"type": "stop"}  # what decode_record returns for the learner's stop message


def decode_record(frame: bytes) -> dict[str, Any] | None:
    """The record in one telemetry frame, STOP for a stop message, or None for anything else."""
    if len(frame) > MAX_FRAME_BYTES:
        return None
    try:
        msg = codec.decode([frame])
    except codec.WireError:
        return None
    if msg.type == "stop":
        return STOP
    return msg.fields["record"] if msg.type == "telemetry" else None


def run_dashboard(telemetry_endpoint: str, refresh_per_s: float = 4.0, stop_after_s: float | None = None,
                  console: Console | None = None, state: DashboardState | None = None,
                  security: Security | None = None) -> int:
    """Draw the telemetry at `telemetry_endpoint` until Ctrl-C, a stop record or `stop_after_s`.

    `state` may be passed to inspect what was received after the call returns (tests do). Returns 0:
    every way out is a normal exit, and the Live context restores the terminal on all of them.
    """
    if refresh_per_s <= 0:
        raise ValueError(f"refresh_per_s must be > 0, got {refresh_per_s}")
    state = state if state is not None else DashboardState()
    state.source = state.source or telemetry_endpoint
    deadline = None if stop_after_s is None else time.monotonic() + stop_after_s
    poll_ms = max(1, int(1000 / refresh_per_s))
    ctx = zmq.Context()  # our own context, so term() cannot wait on sockets of the caller's
    # Only the newest record matters: the telemetry channel's subscription is conflated.
    sock = open_channel(ctx, "telemetry", "connect", telemetry_endpoint, security or Security())
    try:
        with Live(render(state), console=console, screen=False, transient=False,
                  refresh_per_second=refresh_per_s, auto_refresh=True) as live:
            try:
                while deadline is None or time.monotonic() < deadline:
                    timeout = poll_ms
                    if deadline is not None:
                        timeout = max(0, min(poll_ms, int((deadline - time.monotonic()) * 1000)))
                    if sock.poll(timeout, zmq.POLLIN):
                        try:
                            record = decode_record(sock.recv(zmq.NOBLOCK))
                        except zmq.Again:
                            continue
                        if record is None:
                            state.note_garbage()
                        elif record.get("type") == "stop":
                            break
                        else:
                            state.update(record)
                    # Redraw even without news, so the staleness banner's age keeps counting.
                    live.update(render(state))
            except KeyboardInterrupt:
                pass
            live.update(render(state))
    except KeyboardInterrupt:  # Ctrl-C while Live was starting or stopping: still a clean exit
        pass
    finally:
        sock.close(0)
        ctx.term()
    return 0
