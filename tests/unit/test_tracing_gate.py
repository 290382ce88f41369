"""The gate that keeps module calls of other threads out of a background compile's trace."""
from __future__ import annotations

import threading
import time

from higher_dist.learning.compiled_loss import TracingGate


def test_a_build_waits_for_users_and_refuses_new_ones_while_it_runs():
    gate = TracingGate()
    assert gate.try_enter()  # a user inside
    built = threading.Event()
    build_end = []

    def build():
        with gate.building():
            built.set()
            time.sleep(0.2)
            build_end.append(time.monotonic())

    t = threading.Thread(target=build)
    t.start()
    time.sleep(0.05)
    assert not built.is_set()  # waits for the user to leave
    assert not gate.try_enter()  # a waiting build goes first: no new users
    gate.leave()
    assert built.wait(2.0)
    assert not gate.try_enter()  # refused while the build runs
    entered_at = []

    def user():
        with gate.using():  # waits for the build to end
            entered_at.append(time.monotonic())

    u = threading.Thread(target=user)
    u.start()
    t.join()
    u.join()
    assert entered_at and entered_at[0] >= build_end[0]  # the user entered only after the build
    assert gate.try_enter()  # open again once the build ended
    gate.leave()


def test_users_share_the_gate():
    gate = TracingGate()
    assert gate.try_enter() and gate.try_enter()
    with gate.using():
        pass
    gate.leave()
    gate.leave()
    done = threading.Event()
    threading.Thread(target=lambda: (gate.building().__enter__(), done.set())).start()
    assert done.wait(2.0)  # no user left: the build enters at once
