"""How an episode ended: success, a wrong outcome, a cycle, or a search still going at the time-out.

A greedy agent fails in one of three ways. It achieves something other than its mission (a wrong
outcome: what HER and HIGhER relabel); or it achieves nothing, either caught in a cycle or still
searching. It is in a cycle when its input, the last `frame_stack` views it acted on, equals the input
P steps earlier (P <= MAX_PERIOD): the world does not change while nothing is achieved and a greedy
policy is a function of its input and its mission, so from there it repeats the same P actions until
the time-out. Period 1 is an action that changes nothing (a step into a wall), 2 a step back and forth,
4 a turn on the spot. Relabelling cannot help an episode that achieved nothing.

A recurrent policy (network.core=gru) reads the whole episode, so a repeated input never recurs; its
episodes are judged on their last RECURRENT_JUDGED_STACK views, as a frame-stack policy's would be:
the same actions repeated over the same views until the time-out.
"""
from __future__ import annotations

import numpy as np

from higher_dist.learning.episode import SUCCESS, Episode

MAX_PERIOD = 16  # the longest cycle looked for: 4 turns make a turn on the spot, 16 steps a small loop walked
KINDS = ("success", "wrong outcome", "cycling", "searching")
RECURRENT_JUDGED_STACK = 4  # the frame-stack default: a recurrent agent's cycles read on the same scale


def judged_stack(frame_stack: int, core: str) -> int:
    """The views a policy's episodes are judged on: its own input, or RECURRENT_JUDGED_STACK for a
    recurrent core (NetworkConfig.core)."""
    return RECURRENT_JUDGED_STACK if core == "gru" else frame_stack


def cycle_period(frames: np.ndarray, stack: int, max_period: int = MAX_PERIOD) -> int:
    """The shortest P in [1, max_period] for which the last `stack` views an agent acted on equal the
    `stack` views P steps before them; 0 when none does.

    `frames` (T+1, V, V, C): an episode's views, the last one after its last action (not acted on)."""
    acted = np.asarray(frames)[:-1]
    steps = len(acted)
    last = acted[steps - stack:]
    for period in range(1, max_period + 1):
        if period + stack > steps:
            break
        if np.array_equal(last, acted[steps - stack - period:steps - period]):
            return period
    return 0


def end_of(ep: Episode, stack: int) -> tuple[str, int]:
    """(one of KINDS, the cycle's period or 0) for an episode played to its end by an agent with a
    `stack`-frame input."""
    if ep.outcome == SUCCESS:
        return "success", 0
    if ep.pick_step is not None and ep.pick_step >= 0:
        return "wrong outcome", 0
    period = cycle_period(ep.frames, stack)
    return ("cycling" if period else "searching"), period


def classify(ep: Episode, stack: int) -> str:
    """One of KINDS for an episode played to its end by an agent with a `stack`-frame input."""
    return end_of(ep, stack)[0]
