"""Running a plan: up to K runs at once, finished runs skipped, interrupted ones resumed, a progress view.

Each cluster run is a `higher-cluster --no-dashboard` process tree in its own run folder with its own
ports; the executor starts it with `--resume` when the folder holds a learner checkpoint. Children stay
in this process's group, so Ctrl-C in a terminal (or a signal to the group) reaches every role, which
checkpoints and exits; the executor also forwards SIGTERM to each run it started, waits, and kills only
what is left of its own children's trees. A stopped plan loses at most each run's last checkpoint
interval (`checkpoint_every_s`; on SIGTERM the learner writes a final one): rerun the same command.

A run killed before its first checkpoint has nothing to resume: its folder is cleared and it starts
again. When a run resumes, metrics recorded after its checkpoint (a hard kill) are dropped, so the
curve never steps back.
"""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import psutil

from higher_dist import metrics as m
from higher_dist.launch.local_cluster import cli_argv
from higher_dist.launch.topology import free_base_port
from higher_dist.reproduce.plan import GENERATOR_EVAL_PAIRS, Plan, RunSpec
from higher_dist.reproduce.status import frames_done, human_seconds, last_record, run_state
from higher_dist.rundir import RunDir, atomic_write_bytes, read_metrics

STOP_GRACE_S = 60.0  # a cluster's roles get 20 s each to checkpoint; the supervisor waits for them
POLL_S = 0.5  # how often a finished run is noticed
REFRESH_S = 2.0  # how often each run's progress is read from disk and shown
GENERATOR_RUN_S = 60.0  # a generator measurement, for the ETA


def cluster_argv(run: RunSpec, run_dir: Path, port_base: int, resume: bool) -> list[str]:
    return cli_argv("cluster", *run.cluster_flags(), "--no-dashboard", "--run-dir", str(run_dir),
                    "--port-base", str(port_base), *(["--resume"] if resume else []))


def generator_argv(run: RunSpec, run_dir: Path) -> list[str]:
    return [sys.executable, "-m", "higher_dist.reproduce.gen_task", "--pairs", str(run.pairs), "--seed", str(run.seed),
            "--world", run.world, "--steps", str(run.steps), "--eval-pairs", str(GENERATOR_EVAL_PAIRS),
            "--out", str(run_dir), "--", *run.flags]


def trim_metrics_to_checkpoint(run_dir: Path) -> int:
    """Drop metrics recorded after the learner's checkpoint (they will be recorded again); returns the
    checkpoint's frames."""
    state = RunDir(run_dir).load_checkpoint("learner")
    frames = int(state["core"]["counters"]["frames"]) if state else 0
    records = read_metrics(run_dir / "metrics.jsonl")
    kept = [r for r in records if isinstance(r.get(m.FRAMES), (int, float)) and r[m.FRAMES] <= frames]
    if len(kept) != len(records):
        atomic_write_bytes(run_dir / "metrics.jsonl", "".join(json.dumps(r) + "\n" for r in kept).encode())
    return frames


@dataclass
class Job:
    run: RunSpec
    path: Path
    proc: subprocess.Popen
    started: float
    resumed_from: int
    samples: list[tuple[float, int]] = field(default_factory=list)  # (time, frames) seen by the view

    def fps(self, window: int = 30) -> float | None:
        """Frames/s over the last `window` samples (a minute at one per REFRESH_S: metrics come in steps);
        None until a full window has passed, as a run that starts or resumes spends its first seconds
        loading, not stepping, and a rate from them would put the ETA days away."""
        if len(self.samples) < window:
            return None
        (t0, f0), (t1, f1) = self.samples[-window], self.samples[-1]
        return (f1 - f0) / (t1 - t0) if t1 > t0 and f1 > f0 else None


class Executor:
    def __init__(self, plan: Plan, runs: list[RunSpec], parallel: int, view, est_fps: float):
        self.plan, self.parallel, self.view, self.est_fps = plan, parallel, view, est_fps
        self.queue = [r for r in runs if run_state(r, plan.path(r)) != "done"]
        self.runs = runs
        self.jobs: list[Job] = []
        self.finished: dict[str, str] = {r.name: "done (earlier)" for r in runs if r not in self.queue}
        self.stop_signal: int | None = None

    # -- one run --------------------------------------------------------------------------------------
    def start(self, run: RunSpec) -> Job:
        path = self.plan.path(run)
        state = run_state(run, path)
        if state == "stale":
            shutil.rmtree(path)  # started but never checkpointed: nothing to keep
        path.mkdir(parents=True, exist_ok=True)
        (path / "logs").mkdir(exist_ok=True)
        resumed_from, resume = 0, False
        if run.kind == "generator":
            argv = generator_argv(run, path)
        else:
            resume = state == "resumable"
            if resume:
                resumed_from = trim_metrics_to_checkpoint(path)
            argv = cluster_argv(run, path, free_base_port(), resume)
        with open(path / "logs" / "reproduce.log", "ab") as log:
            proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        verb = f"resumed at {resumed_from} frames" if resume else ("restarted" if state == "stale" else "started")
        self.view.event(f"{run.name}: {verb}")
        return Job(run, path, proc, time.time(), resumed_from)

    def close(self, job: Job, code: int) -> None:
        state = run_state(job.run, job.path)
        if state == "done":
            self.finished[job.run.name] = "done"
            if job.run.kind == "cluster" and job.samples:
                # The next runs' ETA starts from what this one did here, not from the estimate.
                self.est_fps = max(1.0, (job.samples[-1][1] - job.resumed_from) / max(time.time() - job.started, 1.0))
            self.view.event(f"{job.run.name}: done in {human_seconds(time.time() - job.started)}")
        elif self.stop_signal is not None:
            self.finished[job.run.name] = "stopped"
        else:
            self.finished[job.run.name] = f"failed (exit {code})"
            self.view.event(f"{job.run.name}: FAILED with exit code {code}; see {job.path / 'logs'}")

    # -- the loop ----------------------------------------------------------------------------------------
    def run(self) -> int:
        def on_signal(signum, _frame):
            self.stop_signal = signum

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            next_refresh = 0.0
            with self.view:
                while (self.queue or self.jobs) and self.stop_signal is None:
                    while self.queue and len(self.jobs) < self.parallel and self.stop_signal is None:
                        self.jobs.append(self.start(self.queue.pop(0)))
                    for job in list(self.jobs):
                        code = job.proc.poll()
                        if code is not None:
                            self.jobs.remove(job)
                            self.close(job, code)
                    if time.time() >= next_refresh:
                        self.refresh()
                        next_refresh = time.time() + REFRESH_S
                    time.sleep(POLL_S)
                if self.stop_signal is not None:
                    self.view.event(f"stopping on signal {self.stop_signal}: runs checkpoint and exit")
                    self.stop_all()
                    self.refresh()
        finally:
            for s, handler in old.items():
                signal.signal(s, handler)
        if self.stop_signal is not None:
            return 128 + self.stop_signal
        return 0 if all(v.startswith("done") for v in self.finished.values()) else 1

    def stop_all(self) -> None:
        for job in self.jobs:
            if job.proc.poll() is None:
                job.proc.send_signal(signal.SIGTERM)
        deadline = time.time() + STOP_GRACE_S
        for job in self.jobs:
            try:
                job.proc.wait(timeout=max(0.1, deadline - time.time()))
            except subprocess.TimeoutExpired:
                _kill_tree(job.proc.pid)
            self.close(job, job.proc.returncode if job.proc.returncode is not None else -9)
        self.jobs = []

    # -- progress ------------------------------------------------------------------------------------
    def refresh(self) -> None:
        now = time.time()
        rows = []
        for run in self.runs:
            path = self.plan.path(run)
            job = next((j for j in self.jobs if j.run.name == run.name), None)
            done = frames_done(run, path) if path.exists() else 0
            if job is not None:
                job.samples.append((now, done))
            total = run.pairs if run.kind == "generator" else run.frames
            state = "running" if job else self.finished.get(run.name, run_state(run, path))
            record = last_record(path) if run.kind == "cluster" and path.exists() else {}
            rows.append({"name": run.name, "state": state, "done": min(done, total), "total": total,
                         "fps": job.fps() if job else None, "eval": record.get(m.SUCCESS_EVAL_TRAIN),
                         "heldout": record.get(m.SUCCESS_EVAL_HELDOUT)})
        self.view.update(rows, self.eta(rows))

    def eta(self, rows: list[dict]) -> float | None:
        """Seconds left: frames left over the frame rate the running runs show (the estimate before
        any shows one), generator runs at a minute each, shared among the runs that run at once."""
        seen = [j.fps() for j in self.jobs if j.run.kind == "cluster" and j.fps()]
        fps = sum(seen) / len(seen) if seen else self.est_fps
        kinds = {r.name: r.kind for r in self.runs}
        todo = [r for r in rows if not str(r["state"]).startswith("done")]
        frames_left = sum(r["total"] - r["done"] for r in todo if kinds[r["name"]] == "cluster")
        generator_left = sum(1 for r in todo if kinds[r["name"]] == "generator")
        at_once = max(1, min(self.parallel, len(todo)))
        return (frames_left / fps + generator_left * GENERATOR_RUN_S) / at_once if fps else None


def _kill_tree(pid: int) -> None:
    """SIGKILL a child that did not stop in time, and its descendants (its roles): ours, by pid."""
    try:
        parent = psutil.Process(pid)
        family = parent.children(recursive=True) + [parent]
    except psutil.Error:
        return
    for p in family:
        try:
            p.kill()
        except psutil.Error:
            pass
    psutil.wait_procs(family, timeout=10)
