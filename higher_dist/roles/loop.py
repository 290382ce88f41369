"""What every role's loop shares: a periodic timer, the check of a peer's message, and the stop on an
internal error.

Two kinds of failure, two answers. A peer's message that fails decoding or validation is the peer's fault:
it is dropped and counted by reason, and the role goes on (`HandlerGuard`, around the decoding and checking
of one message only). An exception raised by the role's own code on input that passed those checks (a
replay insert, an update, a relabel, a checkpoint write, an evaluation) is a bug or a broken machine, not a
bad message: the role stops with a one-line cause and exit status `INTERNAL_ERROR_EXIT`, writes nothing
from the state that raised, and its last good checkpoint is what a restart with --resume goes on from
(`internal` names the step that ran, `stop_on_internal_error` says why and returns the status).
"""
from __future__ import annotations

import contextlib
import logging
import sys
import time
from typing import Any, Callable, Iterator

from higher_dist.launch.parent import INTERNAL_ERROR_EXIT
from higher_dist.wire.codec import WireError
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
    """Runs the decoding and checking of one peer's message, so that no message can end the process: a
    `WireError` is counted under its reason; any other exception there is logged with the message's type
    and sender and counted in `errors` and as a `handler_error` reject. Either way the message is dropped
    (None) and the loop goes on. What the role then does with a message that passed is outside the guard:
    an exception there is an internal error (`internal`)."""

    def __init__(self, rejects: RejectCounter, log: logging.Logger, where: str = ""):
        self.rejects, self.log, self.where = rejects, log, where
        self.errors = 0

    def __call__(self, msg, check: Callable[..., Any], *args: Any) -> Any:
        """check(*args), or None when it raised."""
        try:
            return check(*args)
        except WireError as e:
            self.rejects.add(e.reason, e.detail, self.where)
            return None
        except Exception as exc:  # noqa: BLE001 - whatever a malformed message makes a check do
            self.errors += 1
            self.rejects.add("handler_error", f"{msg.type} from {msg.sender!r}: {type(exc).__name__}: {exc}",
                             self.where)
            self.log.exception("checking the %s message from %r failed; dropped it", msg.type, msg.sender)
            return None


class InternalError(Exception):
    """An exception of the role's own code, with the step that raised it (`step`) and the exception."""

    def __init__(self, step: str, cause: BaseException):
        super().__init__(f"internal error in {step}: {type(cause).__name__}: {cause}")
        self.step, self.cause = step, cause


@contextlib.contextmanager
def internal(step: str) -> Iterator[None]:
    """Names the step of the role's own processing that runs inside: an exception there becomes an
    `InternalError` of that step (one already named keeps its step)."""
    try:
        yield
    except InternalError:
        raise
    except Exception as exc:
        raise InternalError(step, exc) from exc


def stop_on_internal_error(role: str, exc: Exception, kept: str, log: logging.Logger) -> int:
    """Says why `role` stops, the traceback in its log and then one line on stderr naming the step, the
    error and `kept` (what stays on disk for a restart), and returns the exit status."""
    err = exc if isinstance(exc, InternalError) else InternalError("its loop", exc)
    log.error("%s; traceback:", err, exc_info=err.cause)
    line = f"{role}: {err} ({kept})"
    print(line, file=sys.stderr, flush=True)
    return INTERNAL_ERROR_EXIT
