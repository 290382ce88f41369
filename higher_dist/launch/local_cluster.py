"""`higher-cluster`: start every role on this machine as its own process and supervise them.

A role that dies is restarted with exponential backoff (the learner and the relabeler with --resume,
so they continue from their checkpoints); after `max_restarts` crashes of one role the whole cluster is
stopped with a message naming it. A role that stopped on an internal error (exit status 70, see
roles/loop.py) is one such crash: it wrote no checkpoint of the state that raised, so its restart goes on
from its last good one, and the supervisor's line quotes the cause the role gave. Ctrl-C or SIGTERM stops every role cleanly: each gets SIGTERM, writes
its final checkpoint and exits; whatever is still alive after a grace period is killed, so no process
is left behind. The learner ends the run when the frame budget is reached (exit 0).
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from higher_dist.config import Config
from higher_dist.launch.channels import check_binds
from higher_dist.launch.layout import Layout, available_cores, plan_layout
from higher_dist.launch.memory import role_env
from higher_dist.launch.parent import INTERNAL_ERROR_EXIT, LAUNCHER_PID_ENV
from higher_dist.launch.topology import DEFAULT_BASE_PORT, Endpoints, check_free, claim_ports, parse_endpoint
from higher_dist.rundir import RunDir, last_record
from higher_dist.wire.security import Security

GRACE_S = 20.0  # time each role gets to checkpoint and exit after SIGTERM


@dataclass
class RoleProcess:
    name: str
    argv: list[str]
    log_path: Path
    essential: bool = True  # the dashboard is not: it is never restarted
    proc: subprocess.Popen | None = None
    restarts: int = 0
    next_start: float = 0.0
    crash_times: list[float] = field(default_factory=list)

    def start(self, extra_env: dict[str, str] | None = None, log_to_file: bool = True) -> None:
        # PYTHONFAULTHANDLER: a role killed by a signal (a segfault in a native library) leaves its
        # Python stack in its log, where the supervisor's "exited with code -11" alone says nothing.
        env = dict(role_env(), HIGHER_RESTARTS=str(self.restarts), PYTHONFAULTHANDLER="1",
                   **{LAUNCHER_PID_ENV: str(os.getpid())}, **(extra_env or {}))
        out = open(self.log_path, "ab") if log_to_file else None
        self.proc = subprocess.Popen(self.argv, stdout=out, stderr=subprocess.STDOUT if out else None, env=env)
        if out:
            out.close()  # the child holds its own descriptor


def stated_cause(role: RoleProcess, code: int, tail_bytes: int = 65536) -> str:
    """", CAUSE" with the one line a role that stopped on an internal error wrote last in its log, else ""."""
    if code != INTERNAL_ERROR_EXIT:
        return ""
    try:
        with open(role.log_path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - tail_bytes))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return ""
    said = [line.strip() for line in lines if re.match(r"[a-z]+( \d+)?: internal error in ", line)]
    return f", {said[-1]}" if said else ""


def cli_argv(command: str, *args: str) -> list[str]:
    """The argv that runs `higher-COMMAND ARGS` with this interpreter (no console script needed on PATH)."""
    return [sys.executable, "-c", f"import sys; from higher_dist.cli import {command}_main as m; sys.exit(m())",
            *args]


def host_layout(cfg: Config) -> Layout:
    """This host's layout for the run: its cores, the config's actors, the learner's device resolved."""
    from higher_dist.learning.devices import resolve_device  # torch: only when a cluster starts

    return plan_layout(available_cores(), cfg.actors, str(resolve_device(cfg.device)), cfg.torch_threads)


def build_roles(cfg: Config, run_dir: RunDir, endpoints: Endpoints, resume: bool, dashboard: bool,
                security: Security, bind_host: str | None = None, layout: Layout | None = None) -> list[RoleProcess]:
    layout = layout or host_layout(cfg)
    logs = run_dir.path / "logs"
    logs.mkdir(exist_ok=True)
    requested = run_dir.path / "config.requested.json"
    requested.write_text(cfg.to_json())
    host, port = parse_endpoint(endpoints.control)
    keys = ["--keys", str(security.keys)] if security.encrypted else []
    binding = (["--bind-host", bind_host] if bind_host else []) + (["--insecure"] if security.insecure else [])
    learner = cli_argv("learner", "--config", str(requested), "--run-dir", str(run_dir.path),
                   "--host", host, "--port-base", str(port), *keys, *binding,
                   "--threads", str(layout.learner_threads), "--layout", layout.describe(),
                   *(["--resume"] if resume else []))
    relabeler = cli_argv("relabeler", "--learner", endpoints.control, "--state-dir", str(run_dir.path),
                     "--threads", str(layout.relabeler_threads), *keys, *binding, *(["--resume"] if resume else []))
    roles = [RoleProcess("learner", learner, logs / "learner.log"),
             RoleProcess("relabeler", relabeler, logs / "relabeler.log")]
    for i in range(cfg.actors):
        argv = cli_argv("actor", "--learner", endpoints.control, "--actor-id", str(i),
                    "--threads", str(layout.actor_threads), *keys)
        roles.append(RoleProcess(f"actor{i}", argv, logs / f"actor{i}.log"))
    if dashboard:
        roles.append(RoleProcess("dashboard", cli_argv("dashboard", "--learner", endpoints.control, *keys),
                                 logs / "dashboard.log", essential=False))
    return roles


class Supervisor:
    def __init__(self, roles: list[RoleProcess], max_restarts: int, run_dir: RunDir, quiet: bool):
        self.roles = roles
        self.max_restarts = max_restarts
        self.run_dir = run_dir
        self.quiet = quiet  # a dashboard owns the terminal
        self.stopping = False
        self.exit_code = 0

    def say(self, text: str) -> None:
        line = f"[higher-cluster {time.strftime('%H:%M:%S')}] {text}"
        with open(self.run_dir.path / "logs" / "cluster.log", "a") as f:
            f.write(line + "\n")
        if not self.quiet:
            print(line, flush=True)

    def start_all(self) -> None:
        for i, role in enumerate(self.roles):
            role.start(log_to_file=role.name != "dashboard")
            if i == 0:
                time.sleep(0.5)  # the learner binds first, so others' first hello finds it

    def poll(self) -> bool:
        """One supervision pass; False once the run is over."""
        now = time.time()
        for role in self.roles:
            if role.proc is None:
                if now >= role.next_start and not self.stopping:
                    self.say(f"restarting {role.name} (restart {role.restarts})")
                    # Restarted stateful roles continue from their checkpoint, once there is one.
                    has_ckpt = self.run_dir.checkpoint_path(role.name).exists()
                    if role.name in ("learner", "relabeler") and has_ckpt and "--resume" not in role.argv:
                        role.argv.append("--resume")
                    role.start(log_to_file=role.name != "dashboard")
                continue
            code = role.proc.poll()
            if code is None:
                continue
            role.proc = None
            if role.name == "learner" and code == 0:
                self.say("learner finished the run")
                return False
            if code == 0 and role.name != "learner":
                # A role that was told to stop (end of run) exits 0: not a crash, nothing to restart.
                role.next_start = float("inf")
                continue
            if not role.essential:
                if code != 0:
                    self.say(f"{role.name} exited with {code}; the run goes on without it")
                role.next_start = float("inf")
                continue
            role.crash_times.append(now)
            role.restarts += 1
            if role.restarts > self.max_restarts:
                self.say(f"giving up: {role.name} crashed {role.restarts} times (last exit code {code}"
                         f"{stated_cause(role, code)}); see {role.log_path}")
                self.exit_code = 1
                return False
            backoff = min(2.0 ** (role.restarts - 1), 30.0)
            self.say(f"{role.name} exited with code {code}{stated_cause(role, code)}; restart in {backoff:.0f} s")
            role.next_start = now + backoff
        return True

    def stop_all(self) -> None:
        self.stopping = True
        # Actors first, then the relabeler, the learner last: it writes the final checkpoint.
        order = [r for r in self.roles if r.name.startswith("actor") or r.name == "dashboard"]
        order += [r for r in self.roles if r.name == "relabeler"] + [r for r in self.roles if r.name == "learner"]
        for role in order:
            if role.proc is not None and role.proc.poll() is None:
                role.proc.send_signal(signal.SIGTERM)
        deadline = time.time() + GRACE_S
        for role in order:
            if role.proc is None:
                continue
            try:
                role.proc.wait(timeout=max(deadline - time.time(), 0.1))
            except subprocess.TimeoutExpired:
                self.say(f"{role.name} did not stop in time; killing it")
                role.proc.kill()
                role.proc.wait()


def run_local_cluster(cfg: Config, run_dir: str, resume: bool = False, dashboard: bool = True,
                      host: str = "127.0.0.1", port_base: int | None = None, max_restarts: int = 5,
                      security: Security | None = None, bind_host: str | None = None) -> int:
    security = security or Security()
    endpoints = Endpoints.from_base(host, port_base or DEFAULT_BASE_PORT)
    # Refused here, once, rather than by each role in a restart loop.
    check_binds(endpoints, bind_host, security)
    rd = RunDir(run_dir)
    if resume and rd.load_checkpoint("learner") is None:
        raise ValueError(f"--resume: no learner checkpoint in {rd.path}")
    port_claims = claim_ports(endpoints, bind_host)  # held until this function returns (a race otherwise)
    try:
        check_free(endpoints, bind_host)
    except ValueError:
        for claim in port_claims:
            claim.close()
        raise
    dashboard = dashboard and sys.stdout.isatty()
    layout = host_layout(cfg)
    sup = Supervisor(build_roles(cfg, rd, endpoints, resume, dashboard, security, bind_host, layout), max_restarts,
                     rd, quiet=dashboard)
    stop_requested = []

    def on_signal(signum, _frame):
        stop_requested.append(signum)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    sup.say(f"run dir {rd.path}; control {endpoints.control}; {cfg.actors} actors x {cfg.envs_per_actor} envs; "
            f"preset {cfg.preset} on the {cfg.world.name} world; {cfg.frames} frames; layout: {layout.describe()}")
    sup.start_all()
    last_print, seen = 0.0, None
    try:
        while not stop_requested and sup.poll():
            time.sleep(0.2)
            if not dashboard and time.time() - last_print > max(cfg.stats_every_s, 2.0):
                last_print = time.time()
                record = last_record(rd.metrics_path)  # the tail only: the file grows for the run's life
                if record is not None and record.get("time") != seen:
                    seen = record.get("time")
                    sup.say(_summary(record))
    finally:
        sup.stop_all()
        for s, handler in old.items():
            signal.signal(s, handler)
        for claim in port_claims:
            claim.close()
    if stop_requested:
        sup.say("stopped on request; checkpoints written")
    record = last_record(rd.metrics_path)
    if record:
        print(json.dumps({k: v for k, v in record.items() if k != "roles"}))
    return sup.exit_code


def _summary(r: dict) -> str:
    def f(key, fmt="{}"):
        v = r.get(key)
        return "-" if v is None else fmt.format(v)

    return (f"frames {f('frames')} | {f('frames_per_s', '{:.0f}')} fps | updates {f('updates')} "
            f"({f('updates_per_s', '{:.1f}')}/s) | greedy {f('success_rate_eval_train', '{:.2f}')}"
            f"±{f('success_rate_eval_train_se', '{:.2f}')} held-out {f('success_rate_eval_heldout', '{:.2f}')} | "
            + (f"averaged {f('success_rate_eval_train_averaged', '{:.2f}')} | "
               if r.get("success_rate_eval_train_averaged") is not None else "") +
            f"exploring {f('success_rate_train', '{:.2f}')} | "
            f"relabelled {f('relabelled_episodes')} | gen acc {f('generator_val_accuracy', '{:.2f}')} | "
            f"rejected {f('rejected_messages')}")
