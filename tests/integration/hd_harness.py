"""Shared machinery of the end-to-end tests: start real role processes on 127.0.0.1, read what they write in
their run directory, wait on it with deadlines, and make sure nothing they started outlives a test.

Every process is started in its own session (its own process group), so a test can always kill the whole
group, whatever state the run is in. The roles a launcher starts stay in the launcher's group.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import psutil
import pytest
import zmq

from higher_dist.launch.topology import free_base_port
from higher_dist.rundir import read_metrics

# A run that shows every mechanism within seconds on 2 shared cores: the small world shrunk to a 3x3 room
# with short episodes (a random policy picks often, so successes feed the generator's dataset at once),
# small networks, tiny batches, a replay that starts learning after 200 frames, and a generator that
# trains from its 8th pair behind a gate that opens at 10 pairs (min_accuracy 0: the paper's ungated
# variant). Relabels still need parseable instructions, which it learns in a few hundred steps here.
FAST_SETTINGS: dict[str, Any] = {
    "world.room_size": 3,
    "world.max_steps": 10,
    "replay.min_size": 200,
    "dqn.batch_size": 32,
    "network.conv_channels": [16],
    "network.hidden": 64,
    "generator.conv_channels": [16],
    "generator.batch_size": 8,
    "generator.n_min": 10,
    "generator.min_accuracy": 0.0,
    "generator.updates_per_kframe": 200.0,  # a tiny world: the generator must parse within seconds
    "eval.episodes": 4,
    "stats_every_s": 0.5,
    "checkpoint_every_s": 2,
}
MAX_STEPS = FAST_SETTINGS["world.max_steps"]
VIEW_SIZE = 7  # the world's default view


def config_flags(frames: int, actors: int = 2, **settings: Any) -> list[str]:
    """--preset/--world/... flags of a fast run; `settings` override FAST_SETTINGS (None removes one)."""
    merged = {**FAST_SETTINGS, **settings}
    flags = ["--preset", "higher", "--world", "small", "--actors", str(actors), "--envs-per-actor", "8",
             "--frames", str(frames)]
    for key, value in merged.items():
        if value is None:
            continue
        text = "[" + ",".join(map(str, value)) + "]" if isinstance(value, list) else str(value)
        flags += ["--set", f"{key}={text}"]
    return flags


def entry(role: str, *args: str) -> list[str]:
    """argv running one of higher_dist.cli's entry points with this interpreter (the venv's)."""
    return [sys.executable, "-c", f"import sys; from higher_dist.cli import {role}_main as m; sys.exit(m())",
            *map(str, args)]


class PidTracker:
    """Processes seen during a test, by (pid, create time), so a reused pid is never mistaken for ours."""

    def __init__(self) -> None:
        self.seen: dict[int, float] = {}

    def add(self, pid: int | None) -> None:
        if not pid or pid in self.seen:
            return
        try:
            self.seen[pid] = psutil.Process(pid).create_time()
        except psutil.Error:
            pass  # already gone: nothing it could leave behind

    def add_tree(self, pid: int) -> None:
        """The process and all its descendants, as they are now."""
        try:
            root = psutil.Process(pid)
            family = [root, *root.children(recursive=True)]
        except psutil.Error:
            return
        for p in family:
            try:
                self.seen.setdefault(p.pid, p.create_time())
            except psutil.Error:
                pass

    def alive(self) -> list[psutil.Process]:
        out = []
        for pid, created in self.seen.items():
            try:
                p = psutil.Process(pid)
                if p.create_time() == created and p.status() != psutil.STATUS_ZOMBIE:
                    out.append(p)
            except psutil.Error:
                continue
        return out

    def kill_all(self) -> None:
        for p in self.alive():
            try:
                p.kill()
            except psutil.Error:
                pass


class Proc:
    """One process started for a test, in its own session, its output in `log_path`."""

    def __init__(self, argv: list[str], log_path: Path, cwd: Path, tracker: PidTracker | None = None,
                 env: dict[str, str] | None = None):
        self.argv, self.log_path = argv, Path(log_path)
        self.tracker = tracker or PidTracker()
        env = dict(os.environ if env is None else env, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        env.pop("HIGHER_RESTARTS", None)
        with open(self.log_path, "ab") as out:
            self.popen = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                          cwd=cwd, env=env, start_new_session=True)
        self.pid = self.popen.pid
        self.created = time.time()
        self.tracker.add(self.pid)

    @property
    def label(self) -> str:
        """The entry point's name for messages, e.g. cluster_main."""
        code = self.argv[2] if len(self.argv) > 2 else ""
        return code.split(" import ")[-1].split(" as ")[0] if " import " in code else " ".join(self.argv[:2])

    def running(self) -> bool:
        return self.popen.poll() is None

    @property
    def returncode(self) -> int | None:
        return self.popen.poll()

    def snapshot(self) -> None:
        """Remember the process and its descendants (the roles of a launcher)."""
        if self.running():
            self.tracker.add_tree(self.pid)

    def send(self, sig: int) -> None:
        if self.running():
            self.popen.send_signal(sig)

    def wait(self, timeout: float) -> int | None:
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def output(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def kill(self) -> None:
        """Kill the whole process group and anything tracked that is still there (test cleanup)."""
        if self.running():
            try:
                os.killpg(self.pid, signal.SIGKILL)  # the group this process leads: ours
            except (ProcessLookupError, PermissionError):
                pass
        else:
            # The leader is gone; members of its group may not be (orphaned roles). Ours are the ones
            # in that group created after it was started.
            for p in psutil.process_iter(["pid", "create_time"]):
                try:
                    if os.getpgid(p.pid) == self.pid and p.info["create_time"] >= self.created - 1:
                        p.kill()
                except (psutil.Error, OSError):
                    continue
        self.wait(10)
        self.tracker.kill_all()

    def stop(self, grace_s: float = 30.0) -> None:
        """SIGTERM, a grace period, then SIGKILL to the group: the finaliser of every fixture."""
        if self.running():
            self.send(signal.SIGTERM)
            self.wait(grace_s)
        self.kill()


def tail(text: str, n: int = 40) -> str:
    return "\n".join(text.splitlines()[-n:])


def read_text(path: Path) -> str:
    try:
        return Path(path).read_text(errors="replace")
    except FileNotFoundError:
        return ""


class RunWatch:
    """Reads a run directory while its processes run: metrics records, logs, the pids in the roles table."""

    def __init__(self, run_dir: Path, procs: Iterable[Proc] = ()):
        self.run_dir = Path(run_dir)
        self.procs = list(procs)
        self.tracker = PidTracker()
        for p in self.procs:
            p.tracker = self.tracker
            self.tracker.add(p.pid)

    def add(self, proc: Proc) -> Proc:
        proc.tracker = self.tracker
        self.tracker.add(proc.pid)
        self.procs.append(proc)
        return proc

    @property
    def metrics_path(self) -> Path:
        return self.run_dir / "metrics.jsonl"

    def records(self) -> list[dict[str, Any]]:
        records = read_metrics(self.metrics_path)
        for r in records[-3:]:
            self.track_roles(r)
        return records

    def last(self) -> dict[str, Any] | None:
        records = self.records()
        return records[-1] if records else None

    def track_roles(self, record: dict[str, Any]) -> None:
        for row in record.get("roles") or []:
            self.tracker.add(row.get("pid"))

    def log(self, name: str) -> str:
        return read_text(self.run_dir / "logs" / f"{name}.log")

    def diagnostics(self) -> str:
        parts = []
        for p in self.procs:
            parts.append(f"--- {p.label} (pid {p.pid}) rc={p.returncode}\n{tail(p.output(), 25)}")
        logs = self.run_dir / "logs"
        if logs.is_dir():
            for f in sorted(logs.glob("*.log")):
                parts.append(f"--- {f.name}\n{tail(read_text(f), 15)}")
        last = read_metrics(self.metrics_path)[-1:] or [None]
        if last[0] is not None:
            parts.append("--- last metrics: " + str({k: v for k, v in last[0].items() if k != "roles"}))
            parts.append("--- roles: " + str(last[0].get("roles")))
        return "\n".join(parts)

    def wait_for(self, what: str, predicate: Callable[[dict[str, Any]], bool], timeout: float,
                 after: int = 0, need_running: bool = True) -> dict[str, Any]:
        """The first metrics record (at index >= `after`) satisfying `predicate`, polling until `timeout`
        seconds have passed; fails the test with the run's logs otherwise, or as soon as a process died."""
        deadline = time.monotonic() + timeout
        while True:
            for p in self.procs:
                p.snapshot()
            records = self.records()
            for r in records[after:]:
                if predicate(r):
                    self.track_roles(r)
                    return r
            after = max(after, len(records))
            if need_running:
                # A crash, or nothing left running that could write the record: no use waiting.
                crashed = [p for p in self.procs if p.returncode not in (None, 0)]
                if crashed or not any(p.running() for p in self.procs):
                    pytest.fail(f"waiting for {what}: processes exited: "
                                f"{[(p.label, p.returncode) for p in self.procs if not p.running()]}\n"
                                + self.diagnostics())
            if time.monotonic() > deadline:
                pytest.fail(f"no metrics record with {what} within {timeout:.0f} s\n" + self.diagnostics())
            time.sleep(0.4)

    def wait_until(self, what: str, condition: Callable[[], Any], timeout: float) -> Any:
        """Poll `condition()` until it returns something truthy (returned), or fail with the logs."""
        deadline = time.monotonic() + timeout
        while True:
            for p in self.procs:
                p.snapshot()
            value = condition()
            if value:
                return value
            if time.monotonic() > deadline:
                pytest.fail(f"{what}: not within {timeout:.0f} s\n" + self.diagnostics())
            time.sleep(0.4)

    def leftovers(self) -> list[str]:
        """Processes seen during the run that still exist, described for an assertion message."""
        out = []
        for p in self.tracker.alive():
            try:
                out.append(f"{p.pid} {' '.join(p.cmdline())[:160]}")
            except psutil.Error:
                continue
        return out

    def cleanup(self) -> None:
        for p in self.procs:
            p.stop(grace_s=20.0)
        self.tracker.kill_all()


def run_cluster(run_dir, *flags, timeout: float = 240.0) -> subprocess.CompletedProcess:
    """`higher-cluster` on a fresh port range, without a dashboard, run to its end; output captured."""
    return subprocess.run(entry("cluster", "--no-dashboard", "--run-dir", str(run_dir), "--port-base",
                                str(free_base_port()), *map(str, flags)),
                          capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def start_cluster(run_dir: Path, cwd: Path, frames: int, actors: int = 2, extra: Iterable[str] = (),
                  **settings: Any) -> tuple[RunWatch, Proc, int]:
    """A `higher-cluster` with a fresh port range; returns (watch, launcher, base port)."""
    port_base = free_base_port()
    argv = entry("cluster", *config_flags(frames, actors, **settings), "--port-base", str(port_base),
                 "--no-dashboard", "--run-dir", str(run_dir), *extra)
    launcher = Proc(argv, cwd / f"launcher-{port_base}.out", cwd)
    return RunWatch(run_dir, [launcher]), launcher, port_base


def role_rows(record: dict[str, Any], role: str) -> list[dict[str, Any]]:
    return [row for row in record.get("roles") or [] if row["role"] == role]


def role_row(record: dict[str, Any], role: str, index: int) -> dict[str, Any] | None:
    return next((row for row in role_rows(record, role) if row["id"] == index), None)


def learner_pid(launcher: Proc) -> int | None:
    """The learner is not in its own roles table: find it among the launcher's children."""
    try:
        for child in psutil.Process(launcher.pid).children():
            if "learner_main" in " ".join(child.cmdline()):
                return child.pid
    except psutil.Error:
        return None
    return None


def push_socket(ctx, endpoint: str):
    """A PUSH socket that plays a hostile peer: a receiver that stopped reading fails the test, not hangs it."""
    sock = ctx.socket(zmq.PUSH)
    sock.setsockopt(zmq.SNDHWM, 1000)
    sock.setsockopt(zmq.SNDTIMEO, 60_000)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    return sock
