"""What a role and whatever supervises it (higher-cluster, systemd, Slurm) agree on: roles end with the
launcher that started them, so a killed or crashed `higher-cluster` leaves no role behind holding its ports
and cores; and the exit status of a role that stopped on an internal error. Kept free of heavy imports:
every role calls it first thing."""
from __future__ import annotations

import os
import signal
import sys

LAUNCHER_PID_ENV = "HIGHER_LAUNCHER_PID"  # set for the roles a launcher starts: they end with it
# A role's own code raised (roles/loop.py): it kept its last good checkpoint and is to be restarted with
# --resume. sysexits' EX_SOFTWARE; not 2, the status of bad flags and refusals, which systemd does not restart.
INTERNAL_ERROR_EXIT = 70


def follow_launcher() -> None:
    """In a role the launcher started: ask Linux for SIGTERM when the launcher dies (killed, crashed),
    so no role outlives it holding ports and cores; the role checkpoints and exits as on any SIGTERM.
    A launcher already gone before the request took effect is caught by the parent check."""
    launcher = os.environ.get(LAUNCHER_PID_ENV)
    if not launcher or not sys.platform.startswith("linux"):
        return
    import ctypes  # Linux's prctl only: nothing else needs it

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != int(launcher):
        os.kill(os.getpid(), signal.SIGTERM)
