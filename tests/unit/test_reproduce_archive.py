"""`higher-reproduce --archive`: a plan's finished runs, thinned for git, report the same end points and
resume as done; unfinished runs stay out."""
from __future__ import annotations

import json
import random
import re
from pathlib import Path

import pytest

from higher_dist import metrics as m
from higher_dist.analysis.runs import Run
from higher_dist.reproduce import plan as plan_mod
from higher_dist.reproduce.archive import THIN_FRAMES, archive, thin_records
from higher_dist.reproduce.cli import main as reproduce_main
from higher_dist.reproduce.figures import EVALUATIONS, final
from higher_dist.reproduce.status import run_state
from higher_dist.rundir import read_metrics


def records(frames=1_000_000, step=700, every_eval=20_000, seed=0):
    """A run's metrics as the supervisor writes them: a record every `step` frames; an evaluation every
    `every_eval` frames whose averaged-weights half arrives a few records after the online half."""
    rng = random.Random(seed)
    out, evaluation = [], {}
    for i, f in enumerate(range(0, frames + 1, step)):
        if f and f % every_eval < step:
            evaluation = {m.EVAL_FRAMES: f, m.SUCCESS_EVAL_TRAIN: rng.random(), m.SUCCESS_EVAL_HELDOUT: rng.random(),
                          m.SUCCESS_EVAL_TRAIN_AVERAGED: evaluation.get(m.SUCCESS_EVAL_TRAIN_AVERAGED),
                          m.SUCCESS_EVAL_HELDOUT_AVERAGED: evaluation.get(m.SUCCESS_EVAL_HELDOUT_AVERAGED)}
            late = i + rng.randint(1, 3)
        if evaluation and i == late:
            evaluation = {**evaluation, m.SUCCESS_EVAL_TRAIN_AVERAGED: rng.random(),
                          m.SUCCESS_EVAL_HELDOUT_AVERAGED: rng.random()}
        out.append({"time": i * 0.6, "frames": f, "replay_success": i, "roles": [{"role": "learner"}], **evaluation})
    out[-1]["frames"] = frames  # the last record is the budget
    return out


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("every_eval", [20_000, 2_800])  # evaluations sparser and denser than the thinning step
def test_thinning_keeps_every_evaluation_and_one_record_per_step(tmp_path, seed, every_eval):
    full = records(seed=seed, every_eval=every_eval)
    thin = thin_records(full)
    assert thin[0]["frames"] == full[0]["frames"] and thin[-1] == {k: v for k, v in full[-1].items() if k != "roles"}
    assert all("roles" not in r for r in thin)
    assert len(thin) < len(full) / (3 if every_eval > THIN_FRAMES else 1.5)
    for key in EVALUATIONS:  # every end point is the full run's
        a, b = final(Run(tmp_path, "her", 0, "paper", full), key), final(Run(tmp_path, "her", 0, "paper", thin), key)
        assert a is not None and a == b, key
        evaluations = lambda rs: {(r.get(m.EVAL_FRAMES), r.get(key)) for r in rs}  # noqa: E731
        assert evaluations(thin) == evaluations(full), key
    gaps = [b["frames"] - a["frames"] for a, b in zip(thin, thin[1:])]
    assert max(gaps) <= THIN_FRAMES + 700  # no step of the curve is lost


def test_archive_keeps_finished_runs_only_and_resumes_as_done(tmp_path, capsys):
    plan = plan_mod.build_plan(tmp_path / "p", ["main"], 1, 100_000, "small", "default", 1, methods=["dqn", "her"])
    plan = plan_mod.merge_and_write(plan)
    done, cut = (plan.path(r) for r in plan.runs)
    for path, last in ((done, 100_000), (cut, 60_000)):
        path.mkdir(parents=True)
        (path / "config.json").write_text(json.dumps({"replay": {"capacity": 5000}}))
        rs = records(frames=last)
        (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rs))
    (done / "learner.ckpt").write_bytes(b"x" * 1000)
    dest = tmp_path / "archive"
    assert reproduce_main(["--archive", str(dest), "--out", str(plan.out)]) == 0
    assert "1 finished runs archived; 1 not finished" in capsys.readouterr().out
    kept = dest / "runs" / done.name
    assert sorted(p.name for p in kept.iterdir()) == ["config.json", "metrics.jsonl"]  # no checkpoint
    assert not (dest / "runs" / cut.name).exists()
    assert json.loads((dest / "plan.json").read_text()) == json.loads((plan.out / "plan.json").read_text())
    copy = plan_mod.read_plan(dest)
    states = {r.name: run_state(r, copy.path(r)) for r in copy.runs}
    assert states == {done.name: "done", cut.name: "pending"}
    assert read_metrics(kept / "metrics.jsonl")[-1]["frames"] == 100_000


def test_archive_refuses_its_own_plan_folder(tmp_path, capsys):
    plan = plan_mod.merge_and_write(plan_mod.build_plan(tmp_path / "p", ["main"], 1, 1000, "small", "default", 1))
    assert reproduce_main(["--archive", str(plan.out), "--out", str(plan.out)]) == 2
    assert "--archive" in capsys.readouterr().err


ARCHIVES = sorted((Path(__file__).resolve().parents[2] / "docs" / "runs").glob("*/plan.json"))


@pytest.mark.parametrize("plan_file", ARCHIVES, ids=[p.parent.name for p in ARCHIVES])
def test_the_committed_archives_reproduce_their_committed_reports(plan_file):
    """docs/runs/<plan>/ is read by a fresh clone: every run its report counts must be in git (an ignore
    rule once kept them out), and the claims and methods it gives must be what its results.md says."""
    from higher_dist.reproduce.claims import claims, load_groups, method_table

    plan = plan_mod.read_plan(plan_file.parent)
    committed = (plan_file.parent / "results.md").read_text()
    groups = load_groups(plan)
    rows = claims(plan, groups)
    assert rows
    for row in rows:
        line = f"| {row['claim']} | {row['paper']} | {row['ours']} |"
        assert line in committed, f"{plan_file.parent.name}: the archive gives {line!r}, not its results.md"
    for line in method_table(plan, groups)[2:]:
        assert line in committed, f"{plan_file.parent.name}: the archive gives {line!r}, not its results.md"
    assert all((plan_file.parent / p).exists() for p in re.findall(r"\]\((figures/[^)]+)\)", committed))



def test_results_md_holds_its_archives_tables_as_they_are_now():
    """docs/results.md copies its tables from the archives' reports (`make docs`): a regenerated report
    and a stale results.md cannot both be committed."""
    from higher_dist.reproduce import results_blocks

    assert results_blocks.main(["--check"]) == 0
    names = {m.group(2) for m in results_blocks.BLOCK.finditer(results_blocks.RESULTS.read_text())}
    assert {"claims", "methods", "paper-methods"} <= names


def test_results_blocks_fill_each_block_from_the_report_its_prefix_names():
    from higher_dist.reproduce.results_blocks import fill

    reports = {"": "Written today.\nTime: 1 run.\n\n| method | a |\n| --- | --- |\n| DQN | 1% |\nafter\n",
               "paper-": "| method | a |\n| --- | --- |\n| DQN | 2% |\n"}
    text = ("x\n<!-- gen:methods -->\nstale\n<!-- /gen -->\ny\n<!-- gen:paper-methods -->\n<!-- /gen -->\n"
            "<!-- gen:machine -->\nold\n<!-- /gen -->\n")
    out = fill(text, reports)
    assert out == ("x\n<!-- gen:methods -->\n| method | a |\n| --- | --- |\n| DQN | 1% |\n<!-- /gen -->\ny\n"
                   "<!-- gen:paper-methods -->\n| method | a |\n| --- | --- |\n| DQN | 2% |\n<!-- /gen -->\n"
                   "<!-- gen:machine -->\nWritten today.\nTime: 1 run.\n<!-- /gen -->\n")
    with pytest.raises(ValueError, match="gen:trigger"):
        fill("<!-- gen:trigger -->\n<!-- /gen -->", reports)  # a part the report does not have
    with pytest.raises(ValueError, match="unknown block gen:colour"):
        fill("<!-- gen:colour -->\n<!-- /gen -->", reports)
