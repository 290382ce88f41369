"""End to end with the recurrent core (network.core=gru): `higher-cluster` on the small world with real
processes and sockets on 127.0.0.1 runs to its budget, its actors act on published GRU weights, its
learner trains on whole episodes and evaluates them, and the run resumes from its checkpoint (replay
kept) while a switch back to the frame stack is refused by name."""
from __future__ import annotations


import pytest

from hd_harness import run_cluster as cluster
from higher_dist.rundir import RunDir

pytestmark = pytest.mark.slow

FIRST, MORE = 4000, 6000
GRU = ["--set", "network.core=gru"]  # the frame stack of 1 comes with it


@pytest.fixture(scope="module")
def gru_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("recurrent") / "her-gru"
    p = cluster(run_dir, "--preset", "her", "--world", "small", "--frames", FIRST, "--actors", 2,
                "--envs-per-actor", 8, "--set", "eval.every_frames=2000", "--set", "eval.episodes=16", *GRU)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return run_dir


def test_the_recurrent_run_learns_acts_and_evaluates(gru_run):
    records = RunDir(gru_run).read_metrics()
    final = records[-1]
    assert final["frames"] >= FIRST and final["updates"] > 0
    assert final["rejected_messages"] == 0 and final["handler_errors"] == 0
    assert final["replay_ratio"] > 0  # whole episodes were sampled and counted against the ratio
    evaluated = [r for r in records if "success_rate_eval_train" in r]
    assert evaluated and 0.0 <= evaluated[-1]["success_rate_eval_train"] <= 1.0
    assert "cycling_rate_eval_train" in evaluated[-1]
    # Actors acted on published weights: the version each runs (the learner's minus its lag) moves on.
    running = [r["weights_version"] - row["weights_lag"] for r in records for row in r.get("roles") or []
               if row["role"] == "actor" and row.get("weights_lag") is not None]
    assert running and max(running) > 0
    online = RunDir(gru_run).load_checkpoint("learner")["core"]["dqn"]["online"]
    assert "memory.weight_hh_l0" in online  # the checkpoint holds the GRU


def test_the_recurrent_run_resumes_and_refuses_a_switch_of_core(gru_run):
    refused = cluster(gru_run, "--resume", "--set", "network.core=stack", "--set", "network.frame_stack=4",
                      timeout=60)
    assert refused.returncode == 2 and "network.core" in refused.stderr, refused.stderr[-2000:]
    p = cluster(gru_run, "--resume", "--frames", MORE)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    records = RunDir(gru_run).read_metrics()
    assert records[-1]["frames"] >= MORE
    # The resumed learner went on from its checkpoint's counters, with its replay.
    before = [r for r in records if r["frames"] < MORE and r.get("updates")]
    assert records[-1]["updates"] > max(r["updates"] for r in before)
