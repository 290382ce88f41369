"""A resumed run is the run it continues: `higher-cluster --resume` reads the run's config.json, refuses a
flag that would change the experiment (naming the field, the run's value and the one asked for), applies
and records the few that may change (the frame budget, the layout), and never rewrites the run's config
from the flags. One real cluster run on the small world, resumed as a user would."""
from __future__ import annotations

import json

import pytest

from hd_harness import run_cluster as cluster
from higher_dist.rundir import read_metrics

pytestmark = pytest.mark.slow

FIRST, MORE = 3000, 5000


@pytest.fixture(scope="module")
def her_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("resume") / "her-small"
    p = cluster(run_dir, "--preset", "her", "--world", "small", "--frames", FIRST, "--actors", 1,
                "--set", "eval.every_frames=1000", "--set", "eval.episodes=8")
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return run_dir


@pytest.mark.parametrize("flags, named", [
    (["--set", "dqn.lr=0.1"], ["dqn.lr", "0.0005", "0.1"]),
    (["--preset", "higher"], ["--preset higher", "'her'"]),
    (["--world", "paper"], ["--world paper", "'small'"]),
    (["--seed", "3"], ["seed", "0", "3"]),
    (["--set", "replay.samples_per_insert=2"], ["replay.samples_per_insert"]),
])
def test_a_flag_that_changes_the_experiment_is_refused_by_name(her_run, flags, named):
    before = (her_run / "config.json").read_text()
    p = cluster(her_run, "--resume", *flags, timeout=60)
    assert p.returncode == 2, (p.returncode, p.stdout[-2000:], p.stderr[-2000:])
    assert "Traceback" not in p.stderr and all(word in p.stderr for word in named), p.stderr
    assert (her_run / "config.json").read_text() == before
    assert not (her_run / "history.jsonl").exists() or "dqn.lr" not in (her_run / "history.jsonl").read_text()


def test_resume_without_flags_continues_the_run_as_it_was(her_run):
    p = cluster(her_run, "--resume", "--print-config", timeout=60)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout) == json.loads((her_run / "config.json").read_text())


def test_a_longer_budget_is_applied_recorded_and_the_run_keeps_its_preset(her_run):
    p = cluster(her_run, "--resume", "--frames", MORE)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    config = json.loads((her_run / "config.json").read_text())
    assert (config["preset"], config["world"]["name"], config["frames"]) == ("her", "small", MORE)
    history = [json.loads(line) for line in (her_run / "history.jsonl").read_text().splitlines()]
    assert history[-1]["event"] == "resume" and history[-1]["changes"] == {"frames": [FIRST, MORE]}
    assert read_metrics(her_run / "metrics.jsonl")[-1]["frames"] >= MORE
