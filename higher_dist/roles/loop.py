"""What every role's loop shares: a periodic timer and a guard around one message's handler."""
from __future__ import annotations

import logging
import time
from typing import Any, Callable

from higher_dist.wire.sockets import RejectCounter


class Every:
    """A period of `period_s` seconds since it last fired. `start` is when the first period begins
    (0.0: the first call fires at once)."""

    def __init__(self, period_s: float, start: float | None = None):
        self.period_s = period_s
        self.last = time.time() if start is None else start

    def due(self, now: float | None = None) -> bool:
        """True when more than a period has passed; the timer is left as it is."""
        return (time.time() if now is None else now) - self.last > self.period_s

    def reset(self, now: float | None = None) -> None:
        self.last = time.time() if now is None else now

    def __call__(self, now: float | None = None) -> bool:
        """True, and a new period starts, when the period has passed."""
        now = time.time() if now is None else now
        if not self.due(now):
            return False
        self.last = now
        return True


class HandlerGuard:
    """Runs one message's handler so that no message can end the process: an unexpected exception is
    logged with the message's type and sender, counted in `errors` and as a `handler_error` reject, and
    the loop goes on."""

    def __init__(self, rejects: RejectCounter, log: logging.Logger):
        self.rejects, self.log = rejects, log
        self.errors = 0

    def __call__(self, msg, handler: Callable[..., Any], *args: Any) -> Any:
        """handler(*args), or None when it raised."""
        try:
            return handler(*args)
        except Exception as exc:  # noqa: BLE001 - the point is to survive anything one message does
            self.errors += 1
            self.rejects.add("handler_error", f"{msg.type} from {msg.sender!r}: {type(exc).__name__}: {exc}")
            self.log.exception("handling the %s message from %r failed; dropped it", msg.type, msg.sender)
            return None
