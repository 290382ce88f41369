"""Hindsight on a BabyAI level of each kind end to end: `higher-cluster --preset PRESET --world LEVEL --frames
30000 --no-dashboard` (60000 on PickupDist) as real processes over real sockets on 127.0.0.1, until the learner
ends the run: HIGhER on BabyAI-PickupDist-v0 and BabyAI-GoToLocal-v0, HER on BabyAI-OpenDoorColor-v0. Frames
flow, relabelled copies reach the replay (on the HIGhER runs the generator learns the level's language from its
successes and its gate opens), and the dashboard draws the run's records. The open level runs HER: its episodes
last up to 576 steps, so 30k frames hold about 25 successes, too few for the generator's gate."""
from __future__ import annotations

import io
import time

import pytest
from rich.console import Console

from hd_harness import Proc, RunWatch, entry
from higher_dist.config_presets import make_config
from higher_dist.launch.topology import free_base_port
from higher_dist.roles.dashboard_view import DashboardState, render

pytestmark = [pytest.mark.slow, pytest.mark.timeout(700)]

RUNS = (("BabyAI-PickupDist-v0", "higher"), ("BabyAI-GoToLocal-v0", "higher"), ("BabyAI-OpenDoorColor-v0", "her"))
# The generator's gate opens at 30-45k frames on PickupDist under the wide Ape-X ladder (fewer random successes
# than a narrow one gives); the relabeler describes up to 4 outcomes per failed episode and falls behind its
# training pace under load, so each run leaves it room.
FRAMES = {"BabyAI-PickupDist-v0": 60_000, "BabyAI-GoToLocal-v0": 30_000, "BabyAI-OpenDoorColor-v0": 30_000}


RUN_TIMEOUT_S = 600.0  # about 60 s alone on 2 cores; generous for a loaded machine


@pytest.fixture(scope="module", params=RUNS, ids=[level for level, _ in RUNS])
def babyai_run(request, tmp_path_factory) -> tuple[str, int | None, str, list[dict]]:
    level, preset = request.param
    base = tmp_path_factory.mktemp("babyai")
    run_dir = base / "run"
    # The command as given, plus a free port range so parallel tests never collide; the open level's
    # episodes run to 576 steps, so its final greedy evaluation plays fewer of them.
    extra = ["--set", "eval.episodes=32"] if "Open" in level else []
    argv = entry("cluster", "--preset", preset, "--world", level, "--frames", FRAMES[level], "--no-dashboard",
                 "--port-base", free_base_port(), "--run-dir", run_dir, *extra)
    launcher = Proc(argv, base / "launcher.out", base)
    watch = RunWatch(run_dir, [launcher])
    try:
        deadline = time.monotonic() + RUN_TIMEOUT_S
        while launcher.running() and time.monotonic() < deadline:
            launcher.snapshot()
            time.sleep(0.5)
        rc = launcher.wait(5)
        yield level, rc, watch.diagnostics(), watch.records()
    finally:
        watch.cleanup()  # every process the launcher started, whatever happened


def test_the_run_ends_at_its_budget_with_frames_flowing(babyai_run):
    level, rc, diagnostics, records = babyai_run
    assert rc == 0, diagnostics
    last = records[-1]
    assert last["world"] == level and last["frames"] >= FRAMES[level]
    assert [r["frames"] for r in records] == sorted(r["frames"] for r in records) and records[0]["frames"] < FRAMES[level]
    assert last["updates"] > 0 and last["rejected_messages"] == 0 and last["learner_rejected"] == 0


def test_relabelled_episodes_reach_the_replay(babyai_run):
    _, _, _, records = babyai_run
    last = records[-1]
    if last["preset"] == "higher":
        assert last["relabel_strategy"] == "learned" and last["relabel_gate_open"] is True
    else:  # the expert describes every chosen outcome right
        assert last["relabel_strategy"] == "expert" and last["relabel_accuracy"] == 1.0
    assert last["relabelled_episodes"] > 0 and last["replay_relabelled"] > 0
    assert last["replay_wrong_pick"] == 0  # a wrong outcome never ends a BabyAI episode: failures time out
    assert 0.0 <= last["relabel_accuracy"] <= 1.0
    assert last["preset"] != "higher" or last["generator_val_accuracy"] >= 0.5
    # The relabeler reports the pace its generator trains at; an expert has no generator to pace.
    level = last["world"]
    paced = make_config("higher", level).generator.updates_per_kframe if last["preset"] == "higher" else None
    assert last["generator_pace"] == paced


def test_greedy_evaluation_scores_the_levels_own_missions_only(babyai_run):
    _, _, _, records = babyai_run
    evaluated = [r for r in records if r.get("success_rate_eval_train") is not None]
    assert evaluated, "no greedy evaluation was recorded"
    assert all(r.get("success_rate_eval_heldout") is None for r in records)  # a level has no held-out goals


def test_the_dashboard_draws_the_runs_records(babyai_run):
    level, _, _, records = babyai_run
    state = DashboardState()
    for k, record in enumerate(records):
        state.update(record, now=float(k))
    console = Console(record=True, width=100, file=io.StringIO(), color_system=None)
    console.print(render(state, now=float(len(records))))
    text = console.export_text()
    assert level in text and f"{records[-1]['frames']:,}" in text
