"""`higher-cluster --keys` on one host: it trains (frames flow through the CURVE experience path with its
HWM of 1), the dashboard reads the encrypted telemetry with keys and nothing without; and a bind beyond
loopback without keys is refused, naming the exposed ports."""
from __future__ import annotations

import io
import subprocess

from rich.console import Console

from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.roles.dashboard import run_dashboard
from higher_dist.roles.dashboard_view import DashboardState
from higher_dist.wire.security import Security, generate_keys

from hd_harness import config_flags, entry, start_cluster


def test_exposed_bind_without_keys_is_refused_naming_the_ports(tmp_path):
    port = free_base_port()
    done = subprocess.run(entry("cluster", *config_flags(1000, 1), "--port-base", port, "--bind-host", "0.0.0.0",
                                "--no-dashboard", "--run-dir", tmp_path / "run"),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert f"control 0.0.0.0:{port}" in done.stderr and f"telemetry 0.0.0.0:{port + 3}" in done.stderr
    assert "--keys" in done.stderr and "--insecure" in done.stderr
    assert not (tmp_path / "run" / "logs").exists()  # refused before any role started


def test_learner_names_every_exposed_port_refusing_or_warning_once(tmp_path):
    port = free_base_port("0.0.0.0")
    argv = entry("learner", *config_flags(1000, 1), "--port-base", port, "--bind-host", "0.0.0.0",
                 "--run-dir", tmp_path / "run")
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    for i, name in enumerate(("control", "experience", "weights", "telemetry")):
        assert f"{name} 0.0.0.0:{port + i}" in done.stderr, done.stderr
    assert not (tmp_path / "run" / "config.json").exists()  # refused before writing anything
    learner = subprocess.Popen([*argv, "--insecure"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in learner.stdout:
            lines.append(line)
            if "INSECURE" in line:
                break
        assert all(f"0.0.0.0:{port + i}" in lines[-1] for i in range(4)), lines
    finally:
        learner.terminate()
        rest = learner.communicate(timeout=60)[0]
    assert "INSECURE" not in rest  # one warning naming every port, not one more per socket


def test_cluster_with_keys_trains_and_only_keyed_dashboards_read_it(tmp_path):
    keys = tmp_path / "keys"
    generate_keys(keys)
    watch, launcher, port = start_cluster(tmp_path / "run", tmp_path, frames=2000, actors=1,
                                          extra=["--keys", str(keys)])
    try:
        first = watch.wait_for("frames with --keys", lambda r: r["frames"] > 0, timeout=150)
        assert first["frames"] > 0
        telemetry = Endpoints.from_base("127.0.0.1", port).telemetry
        seen = {}
        for name, security in (("keys", Security(str(keys))), ("plain", Security())):
            state = DashboardState()
            run_dashboard(telemetry, refresh_per_s=10, stop_after_s=3.0, console=Console(file=io.StringIO()),
                          state=state, security=security)
            seen[name] = state.records_seen
        assert seen["keys"] > 0 and seen["plain"] == 0, seen
        assert launcher.wait(240) == 0, watch.diagnostics()
        assert watch.records()[-1]["frames"] >= 2000
    finally:
        watch.cleanup()


def test_a_cluster_with_a_key_per_role_runs_and_an_actors_key_cannot_be_its_relabeler(tmp_path):
    keys = tmp_path / "keys"
    for name in ("relabeler", "actor"):  # each role picks the pair named after it; no shared pair
        generate_keys(keys, clients=(name,), roles=frozenset({name}))
    assert not (keys / "client.key_secret").exists()
    watch, launcher, port = start_cluster(tmp_path / "run", tmp_path, frames=2000, actors=1,
                                          extra=["--keys", str(keys)])
    try:
        first = watch.wait_for("frames with per-role keys", lambda r: r["frames"] > 0, timeout=150)
        assert first["frames"] > 0
        control = Endpoints.from_base("127.0.0.1", port).control
        impostor = subprocess.run(entry("relabeler", "--learner", control, "--keys", keys, "--key", "actor",
                                        "--state-dir", tmp_path / "impostor"),
                                  capture_output=True, text=True, timeout=120)
        assert impostor.returncode == 2, impostor.stderr
        assert "the key 'actor' may take the role(s) actor, not relabeler" in impostor.stderr
        assert launcher.wait(240) == 0, watch.diagnostics()
        last = watch.records()[-1]
        assert last["frames"] >= 2000
        assert last["rejects_by_reason"].get("role_not_allowed", 0) >= 1  # counted by the learner
    finally:
        watch.cleanup()
