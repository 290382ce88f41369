"""`higher-bench soak --minutes M`: does any role's memory grow? A paper-world cluster run for M minutes.

Starts `higher-cluster` (the `higher` preset on the paper world by default) and a `higher-dashboard`
attached to it on a pseudo-terminal of its own (so it draws as it would for a user), and samples the
resident set size (RSS) of every process (the launcher, the dashboard and each role) every
`--sample-every` seconds. Per process it reports the growth in MiB/hour (the least-squares slope of RSS
over time, so one noisy sample does not decide it) three ways: after the warm-up, once the run's
fixed-capacity stores are full (the replay, the generator's dataset, which take memory as they fill:
`stores_full_s`), and over the last hour; the verdict against the target (< 5 MiB/h) is the first. A
restarted role is followed under its role name (its RSS restarts too, which the report flags). The
learner's last metrics record comes with the report, so a soak is also a learning run. Prints a table
and writes JSON (`--out`). `--trace-memory` also has every process write its tracemalloc growth to
RUN/memtrace/ (launch/memory.py).
"""
from __future__ import annotations

import argparse
import json
import os
import pty
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

from higher_dist import metrics as names
from higher_dist.launch.local_cluster import cli_argv
from higher_dist.launch.memory import TRACE_DIR_ENV, TRACE_EVERY_ENV, TRACE_WARMUP_ENV, role_env
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.rundir import read_metrics

TARGET_MIB_PER_H = 5.0
ROLE_MARKERS = {"learner_main": "learner", "relabeler_main": "relabeler", "actor_main": "actor",
                "dashboard_main": "dashboard"}


def roles_of(root: psutil.Process) -> dict[str, psutil.Process]:
    """Role name (actor0, actor1, learner, relabeler) -> process, among `root`'s descendants."""
    out: dict[str, psutil.Process] = {}
    counts: dict[str, int] = {}
    for proc in sorted(root.children(recursive=True), key=lambda p: p.pid):
        try:
            cmd = " ".join(proc.cmdline())
        except psutil.Error:
            continue
        role = next((r for marker, r in ROLE_MARKERS.items() if marker in cmd), None)
        if role is None:
            continue
        if role == "actor":
            # --actor-id N when the launcher passes it; otherwise in order of pid.
            parts = cmd.split()
            index = parts[parts.index("--actor-id") + 1] if "--actor-id" in parts else str(counts.get(role, 0))
            counts[role] = counts.get(role, 0) + 1
            role = f"actor{index}"
        out[role] = proc
    return out


def growth_mib_per_h(times_s: list[float], rss_mib: list[float]) -> float | None:
    """Least-squares slope of RSS over time, in MiB/hour (None with fewer than 3 samples)."""
    if len(times_s) < 3:
        return None
    t = np.asarray(times_s) / 3600.0
    return float(np.polyfit(t, np.asarray(rss_mib), 1)[0])


def _dashboard_on_a_terminal(control: str, env: dict[str, str]) -> subprocess.Popen:
    """`higher-dashboard` drawing to a pseudo-terminal whose output is read and thrown away."""
    master, slave = pty.openpty()
    proc = subprocess.Popen(cli_argv("dashboard", "--learner", control), stdin=slave, stdout=slave, stderr=slave,
                            env=dict(env, COLUMNS="100", LINES="40", TERM="xterm-256color"), start_new_session=True)
    os.close(slave)

    def drain():
        try:
            while os.read(master, 65536):
                pass
        except OSError:
            pass  # the dashboard closed its end
        finally:
            os.close(master)

    threading.Thread(target=drain, daemon=True).start()
    return proc


def stores_full_s(records: list[dict], run_dir: Path) -> float | None:
    """Seconds into the run when its fixed-capacity stores were full: the replay at 95% of its capacity
    (whole episodes leave a gap) and, where the run learns a generator, its dataset at capacity. Those
    stores are allocated up front but take memory as they fill, so growth before this is expected."""
    try:
        cfg = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return None
    replay_cap, pairs_cap = cfg["replay"]["capacity"], cfg["generator"]["capacity"]
    learned = cfg["relabel"]["strategy"] == "learned"
    for r in records:
        if (r.get(names.REPLAY_SIZE) or 0) >= 0.95 * replay_cap and (
                not learned or (r.get(names.RELABEL_DATASET_SIZE) or 0) >= pairs_cap):
            return float(r["elapsed_s"])
    return None


def soak(minutes: float, sample_every_s: float, warmup_minutes: float, preset: str, world: str,
         extra: list[str], run_dir: Path, trace_memory: bool = False) -> dict:
    port_base = free_base_port()
    args = ["--preset", preset, "--world", world, "--frames", str(10**10), "--no-dashboard",
            "--run-dir", str(run_dir), "--port-base", str(port_base), *extra]
    env = role_env()
    if trace_memory:
        env.update({TRACE_DIR_ENV: str(run_dir / "memtrace"), TRACE_WARMUP_ENV: str(warmup_minutes * 60),
                    TRACE_EVERY_ENV: str(max(sample_every_s, min(300.0, minutes * 60 / 10)))})
    log = open(run_dir.parent / f"{run_dir.name}-launcher.log", "wb")
    launcher = subprocess.Popen(cli_argv("cluster", *args), stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True, env=env)
    dashboard = None
    samples: dict[str, list[tuple[float, float, int]]] = {}  # process -> [(t, rss MiB, pid)]
    start = time.monotonic()
    try:
        root = psutil.Process(launcher.pid)
        next_sample = start
        while time.monotonic() - start < minutes * 60:
            if launcher.poll() is not None:
                raise RuntimeError(f"the cluster exited with code {launcher.returncode}; see {run_dir}/logs")
            now = time.monotonic()
            if dashboard is None and now - start > 5:  # once the learner has bound its sockets
                dashboard = _dashboard_on_a_terminal(Endpoints.from_base("127.0.0.1", port_base).control, env)
            if now >= next_sample:
                procs = dict(roles_of(root), launcher=root)
                if dashboard is not None and dashboard.poll() is None:
                    procs["dashboard"] = psutil.Process(dashboard.pid)
                for role, proc in procs.items():
                    try:
                        rss = proc.memory_info().rss / 2**20
                    except psutil.Error:
                        continue
                    samples.setdefault(role, []).append((now - start, rss, proc.pid))
                next_sample += sample_every_s
            time.sleep(min(1.0, max(0.0, next_sample - time.monotonic())))
    finally:
        if dashboard is not None and dashboard.poll() is None:
            dashboard.terminate()
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
            try:
                launcher.wait(90)
            except subprocess.TimeoutExpired:
                launcher.kill()
        log.close()
    report: dict = {"minutes": minutes, "warmup_minutes": warmup_minutes, "preset": preset, "world": world,
                    "target_mib_per_h": TARGET_MIB_PER_H, "roles": {}}
    records = read_metrics(run_dir / "metrics.jsonl")
    full_s = stores_full_s(records, run_dir)
    report["stores_full_minutes"] = None if full_s is None else round(full_s / 60, 1)
    for role, rows in sorted(samples.items()):
        after = [r for r in rows if r[0] >= warmup_minutes * 60]
        slope = growth_mib_per_h([r[0] for r in after], [r[1] for r in after])
        full = [r for r in rows if full_s is not None and r[0] >= full_s]
        slope_full = growth_mib_per_h([r[0] for r in full], [r[1] for r in full]) if len(full) >= 10 else None
        last_hour = [r for r in rows if r[0] >= rows[-1][0] - 3600]
        slope_last = growth_mib_per_h([r[0] for r in last_hour], [r[1] for r in last_hour])
        report["roles"][role] = {
            "growth_once_full_mib_per_h": None if slope_full is None else round(slope_full, 2),
            "growth_last_hour_mib_per_h": None if slope_last is None else round(slope_last, 2),
            "rss_start_mib": round(rows[0][1], 1), "rss_after_warmup_mib": round(after[0][1], 1) if after else None,
            "rss_end_mib": round(rows[-1][1], 1), "samples": len(rows),
            "growth_mib_per_h": None if slope is None else round(slope, 2),
            "restarted": len({r[2] for r in rows}) > 1,
            "verdict": "n/a" if slope is None else ("ok" if slope < TARGET_MIB_PER_H else "GROWS"),
            "rss_mib": [round(r[1], 1) for r in rows],
        }
    if records:
        last = records[-1]
        keys = ("frames", "updates", "elapsed_s", "success_rate_eval_train", "success_rate_eval_heldout",
                "success_rate_train", "relabel_dataset_size", "relabel_gate_open", "generator_val_accuracy",
                "relabel_accuracy", "rejected_messages")
        report["last_metrics"] = {k: last.get(k) for k in keys}
    if trace_memory:
        report["memtrace_dir"] = str(run_dir / "memtrace")
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="higher-bench soak", description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--sample-every", type=float, default=60.0, help="seconds between RSS samples")
    p.add_argument("--warmup-minutes", type=float, default=None,
                   help="samples before this are left out of the slope (default: a third of the run, at most 10)")
    p.add_argument("--preset", default="higher")
    p.add_argument("--world", default="paper")
    p.add_argument("--run-dir", default=None, help="where the cluster's run goes (default: a temp folder)")
    p.add_argument("--out", default=None, help="also write the report as JSON here")
    p.add_argument("--trace-memory", action="store_true",
                   help="every process writes its tracemalloc growth to RUN/memtrace/ every 5 minutes")
    args, extra = p.parse_known_args(argv)
    if args.minutes <= 0 or args.sample_every <= 0:
        p.error("--minutes and --sample-every must be > 0")
    warmup = args.warmup_minutes if args.warmup_minutes is not None else min(10.0, args.minutes / 3)
    run_dir = Path(args.run_dir) if args.run_dir else Path(tempfile.mkdtemp(prefix="higher-soak-")) / "run"
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    report = soak(args.minutes, args.sample_every, warmup, args.preset, args.world, extra, run_dir,
                  trace_memory=args.trace_memory)
    print(f"soak: {args.preset} on the {args.world} world, {args.minutes:g} min, RSS every {args.sample_every:g} s, "
          f"growth after {warmup:g} min of warm-up (target < {TARGET_MIB_PER_H:g} MiB/h)")
    print(f"replay and generator dataset full at {report['stores_full_minutes']} min")
    print(f"{'role':<12}{'start MiB':>10}{'warm MiB':>10}{'end MiB':>10}{'MiB/h':>9}{'once full':>11}"
          f"{'last hour':>11}  verdict")
    for role, r in report["roles"].items():
        print(f"{role:<12}{r['rss_start_mib']:>10}{str(r['rss_after_warmup_mib']):>10}{r['rss_end_mib']:>10}"
              f"{str(r['growth_mib_per_h']):>9}{str(r['growth_once_full_mib_per_h']):>11}"
              f"{str(r['growth_last_hour_mib_per_h']):>11}  {r['verdict']}{' (restarted)' if r['restarted'] else ''}")
    print("last metrics:", json.dumps(report.get("last_metrics")))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=2))
    return 0
