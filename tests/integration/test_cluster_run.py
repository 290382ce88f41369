"""End to end: `higher-cluster` with a learner, a relabeler and two actors as real processes over real sockets
on 127.0.0.1. One run to a small frame budget is shared by the assertions about a finished run; a second
cluster is stopped with SIGTERM."""
from __future__ import annotations

import json
import math
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from hd_harness import Proc, RunWatch, learner_pid, role_rows, start_cluster
from higher_dist.rundir import RunDir

pytestmark = pytest.mark.slow

BUDGET = 4000  # env frames: about 15-25 s of acting here, past the generator's gate and the first relabels
RUN_TIMEOUT_S = 150.0
ROLES = {("learner", 0), ("actor", 0), ("actor", 1), ("relabeler", 0)}
HELD = 5000  # more failures than the run offers: none dropped while the gate is shut


@dataclass
class FinishedRun:
    run_dir: Path
    watch: RunWatch
    launcher: Proc
    returncode: int | None
    seconds: float
    records: list[dict[str, Any]] = field(default_factory=list)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> FinishedRun:
    base = tmp_path_factory.mktemp("cluster_run")
    run_dir = base / "run"
    # With a moving average of the weights, so the run also shows it evaluated end to end, and the paper
    # world's bag-of-words instruction encoder, so its weights travel from the learner to every role (the
    # other end-to-end tests run the small world's GRU); its relabeler holds the failures it is offered while
    # the generator's gate is shut, keeps them out of the replay meanwhile (the learner counts them from the
    # relabeler's messages), and relabels them once it opens (at 30 pairs, not the fast 10: a first
    # message of 10 successes would open it before any failure was offered).
    watch, launcher, _ = start_cluster(run_dir, base, frames=BUDGET,
                                       **{"dqn.average_tau": 0.01, "network.text": "bow",
                                          "relabel.held_while_gated": HELD, "relabel.withheld_while_gated": "true",
                                          "generator.n_min": 30})
    t0 = time.monotonic()
    try:
        # Poll while it runs: the roles table and the launcher's children give every pid to check later.
        while launcher.running() and time.monotonic() - t0 < RUN_TIMEOUT_S:
            launcher.snapshot()
            watch.records()
            time.sleep(0.3)
        rc = launcher.wait(5)
        seconds = time.monotonic() - t0
        if rc is None:
            pytest.fail(f"the cluster did not finish {BUDGET} frames in {RUN_TIMEOUT_S:.0f} s\n"
                        + watch.diagnostics())
        yield FinishedRun(run_dir, watch, launcher, rc, seconds, watch.records())
    finally:
        watch.cleanup()


def test_exits_zero_when_the_learner_reaches_the_budget(finished_run):
    assert finished_run.returncode == 0, finished_run.watch.diagnostics()
    assert "learner finished the run" in finished_run.watch.log("cluster")


def test_metrics_record_increasing_frames_up_to_the_budget(finished_run):
    records = finished_run.records
    assert len(records) >= 5, f"only {len(records)} metrics records"
    frames = [r["frames"] for r in records]
    assert all(b >= a for a, b in zip(frames, frames[1:])), f"frames went backwards: {frames}"
    assert frames[0] < frames[-1]
    assert frames[-1] >= BUDGET
    times = [r["time"] for r in records]
    assert all(b >= a for a, b in zip(times, times[1:]))


def test_the_last_record_holds_greedy_success_of_the_online_and_the_averaged_weights(finished_run):
    last = finished_run.records[-1]
    for key in ("success_rate_eval_train", "success_rate_eval_heldout", "success_rate_eval_train_averaged",
                "success_rate_eval_heldout_averaged", "success_rate_eval_train_averaged_se"):
        assert isinstance(last.get(key), float) and 0.0 <= last[key] <= 1.0, (key, last.get(key))
    assert last["eval_frames"] >= BUDGET  # the end-of-run evaluation


def test_the_records_name_the_hosts_layout(finished_run):
    from higher_dist.launch.layout import available_cores, plan_layout
    from higher_dist.learning.devices import resolve_device

    expected = plan_layout(available_cores(), 2, str(resolve_device("auto"))).describe()
    assert finished_run.records[-1]["layout"] == expected
    assert f"layout: {expected}" in finished_run.watch.log("cluster")


def test_the_learner_updates(finished_run):
    last = finished_run.records[-1]
    assert last["updates"] > 0
    updates = [r["updates"] for r in finished_run.records]
    assert all(b >= a for a, b in zip(updates, updates[1:]))
    assert last["replay_size"] > 0


def test_actors_receive_newer_weights(finished_run):
    records = finished_run.records
    versions = [r["weights_version"] for r in records]
    assert all(b >= a for a, b in zip(versions, versions[1:])), versions
    assert versions[-1] > versions[0]
    # What each actor runs: the learner's version minus the actor's lag. It must be finite and move on.
    received: dict[int, list[int]] = {}
    for r in records:
        for row in role_rows(r, "actor"):
            lag = row["weights_lag"]
            if lag is None:
                continue
            assert isinstance(lag, int) and lag >= 0 and math.isfinite(lag), row
            received.setdefault(row["id"], []).append(r["weights_version"] - lag)
    assert set(received) == {0, 1}, f"actors that reported a weights version: {sorted(received)}"
    for actor, seen in received.items():
        assert max(seen) > min(seen), f"actor {actor} never got newer weights: {seen}"
        assert max(seen) > 0
    lags = [r["weights_lag_mean"] for r in records if r.get("weights_lag_mean") is not None]
    assert lags and all(math.isfinite(x) for x in lags)


def test_every_role_registered_and_was_alive(finished_run):
    rows = [row for r in finished_run.records for row in r["roles"]]
    alive = {(row["role"], row["id"]) for row in rows if row["state"] == "alive"}
    assert alive == ROLES, alive
    assert not [row for row in rows if row["state"] == "dead"], "a role was marked dead in a healthy run"


def test_relabelled_episodes_arrive(finished_run):
    last = finished_run.records[-1]
    assert last["relabelled_episodes"] > 0, {k: v for k, v in last.items() if k != "roles"}
    assert last["relabel_dataset_size"] and last["relabel_dataset_size"] >= 20
    assert last["replay_relabelled"] > 0


def test_failures_offered_while_the_gate_was_shut_are_relabelled_once_it_opens(finished_run):
    # The relabeler's last checkpoint (its counts at one moment; a record mixes its heartbeat with older
    # stats): every failure it was offered was relabelled, dropped for a reason it counts, or is still held.
    # A relabeler that forgot what it held while the gate was shut would come up short by those.
    state = RunDir(finished_run.run_dir).load_checkpoint("relabeler")
    accounted = state["relabelled"] + state["unparseable"] + state["contradicting"] + state["held"]["count"]
    assert accounted == state["considered"], {k: v for k, v in state.items() if not isinstance(v, (dict, list))}
    assert state["gated_off"] > 0, "no failure arrived before the gate opened: nothing was held"
    assert state["withheld"] == state["gated_off"], "a failure offered while shut went into the replay"
    assert state["trainer"]["evaluations"] > 0 and state["held"]["count"] == 0
    last = finished_run.records[-1]
    assert last["relabel_gate_open"] and last["relabel_held"] == 0


def test_no_message_was_rejected(finished_run):
    for r in finished_run.records:
        assert r["rejected_messages"] == 0 and r["learner_rejected"] == 0, r
        assert all(row["rejected"] == 0 for row in r["roles"]), r["roles"]


def test_run_dir_holds_config_and_checkpoints(finished_run):
    rd = RunDir(finished_run.run_dir)
    assert (rd.path / "config.json").is_file(), "config.json missing"
    cfg = json.loads((rd.path / "config.json").read_text())
    assert cfg["preset"] == "higher" and cfg["world"]["name"] == "small" and cfg["frames"] == BUDGET
    assert cfg["actors"] == 2 and cfg["envs_per_actor"] == 8 and cfg["relabel"]["strategy"] == "learned"
    assert cfg["network"]["text"] == "bow"
    learner = rd.load_checkpoint("learner")
    assert learner is not None, "learner.ckpt missing"
    # The final checkpoint is written right after the final metrics record: the same counters.
    last = finished_run.records[-1]
    assert learner["core"]["counters"]["updates"] == last["updates"]
    assert learner["core"]["counters"]["frames"] == last["frames"]
    relabeler = rd.load_checkpoint("relabeler")
    assert relabeler is not None, "relabeler.ckpt missing"
    assert relabeler["name"] == "learned"
    assert len(relabeler["trainer"]["dataset"]["views"]) >= 20
    assert not list(finished_run.run_dir.glob("*.tmp*")), "a temporary checkpoint file was left"


def test_no_process_left_behind(finished_run):
    watch = finished_run.watch
    assert len(watch.tracker.seen) >= 5, f"tracked only {sorted(watch.tracker.seen)}"  # launcher + 4 roles
    assert watch.leftovers() == []


@pytest.fixture
def cleanup():
    watches: list[RunWatch] = []
    yield watches.append
    for w in watches:
        w.cleanup()


def test_sigterm_stops_every_role_cleanly(tmp_path, cleanup):
    run_dir = tmp_path / "run"
    # The default checkpoint period (120 s; the relabeler's is 60 s): any checkpoint is the one from stopping.
    watch, launcher, _ = start_cluster(run_dir, tmp_path, frames=10_000_000, checkpoint_every_s=None)
    cleanup(watch)
    seen = watch.wait_for("updates > 0, every role alive",
                          lambda r: r["updates"] > 0 and {(row["role"], row["id"]) for row in r["roles"]
                                                           if row["state"] == "alive"} == ROLES, timeout=120)
    learner = learner_pid(launcher)
    assert learner is not None
    watch.tracker.add(learner)
    assert not (run_dir / "learner.ckpt").exists() and not (run_dir / "relabeler.ckpt").exists()
    launcher.snapshot()
    roles = {(row["role"], row["id"]): row["pid"] for row in seen["roles"]}
    assert set(roles) == ROLES

    t0 = time.monotonic()
    launcher.send(signal.SIGTERM)
    rc = launcher.wait(30)
    took = time.monotonic() - t0
    assert rc == 0, f"exit code {rc} after SIGTERM ({took:.1f} s)\n" + watch.diagnostics()
    assert watch.leftovers() == []

    log = watch.log("cluster")
    assert "stopped on request" in log
    assert "killing it" not in log, "a role had to be killed after SIGTERM\n" + log
    rd = RunDir(run_dir)
    state = rd.load_checkpoint("learner")
    assert state is not None, "no learner checkpoint after SIGTERM"
    assert state["core"]["counters"]["updates"] >= seen["updates"]
    assert rd.read_metrics()[-1]["updates"] == state["core"]["counters"]["updates"]
    relabeler = rd.load_checkpoint("relabeler")
    assert relabeler is not None, "no relabeler checkpoint after SIGTERM"
    assert "relabeler stopped" in watch.log("relabeler")
    for i in (0, 1):
        assert f"actor {i} stopped after" in watch.log(f"actor{i}")


def test_higher_plot_draws_the_finished_run(finished_run, tmp_path, capsys):
    from higher_dist.plot import main as plot_main

    out = tmp_path / "figures"
    assert plot_main([str(finished_run.run_dir), "--out", str(out)]) == 0
    written = {p.name: p for p in out.glob("*.png")}
    # The run has training success, relabeller accuracy and replay composition over frames.
    assert {"success_rate.png", "generator_accuracy.png", "replay_composition.png",
            "success_rate_averaged.png"} <= set(written), written
    for path in written.values():
        data = path.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
