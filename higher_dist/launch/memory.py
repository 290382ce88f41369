"""Memory of the processes a run starts: the allocator's settings every role gets, and an opt-in trace of
what Python allocates, for hunting growth in a long run (`higher-bench soak --trace-memory`).

The allocator: glibc gives each thread that allocates its own arena (up to 8 per core), and the roles
have several threads (torch's, ZeroMQ's I/O threads, the learner's batch prefetch). Memory freed in one
arena is not reused by another, so a long run's resident size creeps up with no Python object behind it.
Every process started through the CLI bounds the arenas to 2 at its start (`mallopt`, before torch or
ZeroMQ start threads), whoever launched it (higher-cluster, Slurm, systemd); the launcher also passes
`MALLOC_ARENA_MAX=2` to its children. A user's own MALLOC_ARENA_MAX is kept.

The trace: with HIGHER_MEMTRACE_DIR set, a process started through the CLI starts a daemon thread that
waits HIGHER_MEMTRACE_WARMUP_S seconds (default 600), starts tracemalloc (so the imports and the warm-up,
slow to trace, are not), and every HIGHER_MEMTRACE_EVERY_S seconds (default 300) appends to
DIR/PROG-PID.txt the resident size, the traced total, and the 12 sites whose live allocations grew most
since tracing began. tracemalloc sees Python objects and numpy arrays, not torch's tensors or the
allocator's own overhead: resident growth with a flat traced total points below Python.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time
import tracemalloc
from pathlib import Path

ALLOCATOR_ENV = {"MALLOC_ARENA_MAX": "2"}
TRACE_DIR_ENV, TRACE_EVERY_ENV, TRACE_WARMUP_ENV = ("HIGHER_MEMTRACE_DIR", "HIGHER_MEMTRACE_EVERY_S",
                                                    "HIGHER_MEMTRACE_WARMUP_S")
TOP_SITES = 12


def role_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """The environment a role process is started with: `base` (default os.environ) plus the allocator's
    settings where the user has not chosen their own."""
    env = dict(os.environ if base is None else base)
    for key, value in ALLOCATOR_ENV.items():
        env.setdefault(key, value)
    return env


_M_ARENA_MAX = -8  # glibc's mallopt parameter number


def bound_arenas() -> bool:
    """Bound this process's malloc arenas (glibc only); False where it was not done."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return False  # the user's choice, already read by glibc at start
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(_M_ARENA_MAX, int(ALLOCATOR_ENV["MALLOC_ARENA_MAX"])))
    except (OSError, AttributeError):
        return False  # not glibc


def _rss_mib() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return float("nan")


class MemoryTrace:
    """Snapshots of this process's Python allocations, compared with a baseline, written to `path`."""

    def __init__(self, path: Path, every_s: float, warmup_s: float, frames: int = 4):
        self.path, self.every_s, self.warmup_s, self.frames = path, every_s, warmup_s, frames
        self.baseline: tracemalloc.Snapshot | None = None
        self.start = time.monotonic()

    def begin(self) -> None:
        """Start tracing now; what is live from here on is compared with this moment."""
        tracemalloc.start(self.frames)
        self.baseline = self._snapshot()
        with open(self.path, "a") as f:
            f.write(f"tracing from t={(time.monotonic() - self.start) / 60:.1f} min, rss={_rss_mib():.1f} MiB\n")

    def _snapshot(self) -> tracemalloc.Snapshot:
        return tracemalloc.take_snapshot().filter_traces((
            tracemalloc.Filter(False, tracemalloc.__file__), tracemalloc.Filter(False, "<frozen importlib._bootstrap>")))

    def write_once(self) -> None:
        """One line of totals, then the sites whose live allocations grew most since tracing began."""
        assert self.baseline is not None, "begin() first"
        snap = self._snapshot()
        minutes = (time.monotonic() - self.start) / 60
        traced, peak = tracemalloc.get_traced_memory()
        lines = [f"t={minutes:.1f} min rss={_rss_mib():.1f} MiB traced={traced / 2**20:.2f} MiB "
                 f"traced_peak={peak / 2**20:.2f} MiB"]
        for stat in snap.compare_to(self.baseline, "lineno")[:TOP_SITES]:
            frame = stat.traceback[0]
            lines.append(f"  {stat.size_diff / 2**10:+10.1f} KiB {stat.count_diff:+8d} blocks  "
                         f"{frame.filename}:{frame.lineno}")
        with open(self.path, "a") as f:
            f.write("\n".join(lines) + "\n")

    def run_forever(self) -> None:
        time.sleep(self.warmup_s)
        self.begin()
        while True:
            time.sleep(self.every_s)
            try:
                self.write_once()
            except Exception as exc:  # noqa: BLE001 - a diagnostic never ends the role it watches
                with open(self.path, "a") as f:
                    f.write(f"trace failed: {type(exc).__name__}: {exc}\n")


def trace_from_env(prog: str) -> MemoryTrace | None:
    """Start the trace thread when HIGHER_MEMTRACE_DIR is set (the soak sets it); otherwise nothing."""
    directory = os.environ.get(TRACE_DIR_ENV)
    if not directory:
        return None
    Path(directory).mkdir(parents=True, exist_ok=True)
    trace = MemoryTrace(Path(directory) / f"{prog}-{os.getpid()}.txt",
                        every_s=float(os.environ.get(TRACE_EVERY_ENV, "300")),
                        warmup_s=float(os.environ.get(TRACE_WARMUP_ENV, "600")))
    threading.Thread(target=trace.run_forever, name="memtrace", daemon=True).start()
    return trace
