"""Greedy evaluation off every collection and update path: a thread of the learner's process with its own
policy copy and its own environments (Acme's evaluator node, in a thread).

The learner hands it a snapshot of the weights when the evaluation cadence fires; the result lands in
`latest` when done. If an evaluation is still running when the next one is due, the new one is skipped
rather than queued: the curve gets a point less, the learner never waits. An evaluation that raises is the
learner's internal error: `check` raises it again in the learner's thread, which stops the learner.
"""
from __future__ import annotations

import logging
import threading

import numpy as np

from higher_dist import metrics as m
from higher_dist.learning.agent import AgentBuilder
from higher_dist.learning.compiled_loss import TRACING_GATE

log = logging.getLogger("higher.evaluator")


class BackgroundEvaluator:
    def __init__(self, agent: AgentBuilder):
        self.agent = agent
        self.policy = agent.policy()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._latest: dict[str, float] = {}
        self._failure: Exception | None = None
        self.evaluations = 0
        self.skipped = 0

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, weights: dict[str, np.ndarray], frames: int,
              averaged: dict[str, np.ndarray] | None = None) -> bool:
        """Evaluate `weights` (a snapshot the caller no longer edits) at `frames`, and `averaged` (the
        moving average of the weights, when the learner keeps one) on the same goals; False if still busy."""
        if self.busy:
            self.skipped += 1
            return False
        self._thread = threading.Thread(target=self._run, args=(weights, averaged, frames), name="evaluator",
                                        daemon=True)
        self._thread.start()
        return True

    def _run(self, weights: dict[str, np.ndarray], averaged: dict[str, np.ndarray] | None, frames: int) -> None:
        try:
            with TRACING_GATE.using():  # not while the learner's loss compiles (compiled_loss.py)
                result = self.agent.evaluate_weights(self.policy, weights, averaged, frames)
        except Exception as exc:  # noqa: BLE001 - handed to the learner's thread, which stops on it (check)
            log.error("evaluation at %d frames failed", frames)
            self._failure = exc
            return
        with self._lock:
            self._latest = {**result, m.EVAL_FRAMES: int(frames)}
            self.evaluations += 1

    def check(self) -> None:
        """Raises what made an evaluation fail, if one did."""
        if self._failure is not None:
            raise self._failure

    def latest(self) -> dict[str, float]:
        with self._lock:
            return dict(self._latest)

    def wait(self, timeout_s: float = 60.0) -> None:
        if self._thread is not None:
            self._thread.join(timeout_s)
