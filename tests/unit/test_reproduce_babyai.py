"""higher-reproduce on a BabyAI level: only the methods that exist there are planned (main without
DQN+reward, trigger), FetchAttr's own experiments (noise, generator) are refused by name and left out
of "all experiments" with a note, and the report needs no held-out evaluations."""
from __future__ import annotations

import json

import pytest
import torch

from higher_dist.config import ConfigError
from higher_dist.reproduce import cli
from higher_dist.reproduce import plan as plan_mod

torch.set_num_threads(1)  # the default spins every core, and these tests share the machine
LEVEL = "BabyAI-PickupDist-v0"


def test_a_babyai_plan_holds_the_methods_a_level_has(tmp_path):
    assert plan_mod.experiments_for("small", None) == (list(plan_mod.EXPERIMENTS), [])
    chosen, notes = plan_mod.experiments_for(LEVEL, None)
    assert chosen == ["main", "trigger"]
    assert [n.split(" ")[0] for n in notes] == ["noise", "generator", "main"]  # each left-out one, with why
    assert plan_mod.experiments_for(LEVEL, ["trigger"]) == (["trigger"], [])
    plan = plan_mod.build_plan(tmp_path / "p", chosen, 1, 10_000, LEVEL, "default", 1)
    variants = {e: [next(r.variant for r in plan.runs if r.name == n) for n in names]
                for e, names in plan.experiments.items()}
    assert variants == {"main": ["dqn", "her", "higher"],
                        "trigger": ["higher-trigger0", "higher-trigger1000", "higher-trigger2000"]}
    configs = plan_mod.check_configs(plan)  # every run's config is one higher-cluster accepts on the level
    assert {c.world.name for c in configs.values()} == {LEVEL}
    assert configs["higher-trigger1000-s0"].generator.n_min == 1000
    with pytest.raises(ConfigError, match="selects no run"):
        plan_mod.build_plan(tmp_path / "p", ["main"], 1, 10_000, LEVEL, "default", 1, methods=["reward"])
    for experiment in ("noise", "generator"):
        with pytest.raises(ConfigError, match=f"experiment {experiment}: not on a BabyAI level"):
            plan_mod.build_plan(tmp_path / "p", ["main", experiment], 1, 10_000, LEVEL, "default", 1)


def test_fetchattrs_own_experiments_are_refused_in_one_line(tmp_path, capsys):
    for experiment, why in (("noise", "attribute noise"), ("generator", "expert pairs")):
        assert cli.main(["--world", LEVEL, "--dry-run", "--out", str(tmp_path / "p"), experiment]) == 2
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        assert len(err) == 1 and f"experiment {experiment}: not on a BabyAI level ({LEVEL})" in err[0], err
        assert why in err[0] and captured.out == ""
    assert not (tmp_path / "p").exists()


def test_a_level_that_is_not_supported_is_refused_before_anything_runs(tmp_path, capsys):
    out = tmp_path / "p"
    assert cli.main(["--world", "BabyAI-PutNextLocal-v0", "--dry-run", "--out", str(out), "main"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'BabyAI-PutNextLocal-v0'" in err[0] and "is not supported" in err[0]
    assert not out.exists()


def test_a_levels_plan_runs_its_own_budget(tmp_path, capsys):
    assert cli.main(["--world", LEVEL, "--seeds", "1", "--dry-run", "--out", str(tmp_path / "p"), "main"]) == 0
    assert "1,000,000 frames per run" in capsys.readouterr().out


def test_dry_run_of_main_on_a_level_lists_six_runs(tmp_path, capsys):
    out = tmp_path / "never"
    assert cli.main(["--world", LEVEL, "--seeds", "2", "--dry-run", "--out", str(out), "main"]) == 0
    text = capsys.readouterr().out
    assert "6 runs (6 cluster runs, 0 generator runs)" in text
    runs = [line.split()[0] for line in text.splitlines() if line.split()[1:2] == ["cluster"]]
    assert runs == ["dqn-s0", "her-s0", "higher-s0", "dqn-s1", "her-s1", "higher-s1"]
    assert f"note: main on {LEVEL} without reward" in text
    # All experiments: main and trigger, with a note for each experiment left out.
    assert cli.main(["--world", LEVEL, "--seeds", "1", "--dry-run", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"note: noise skipped on {LEVEL}" in text and f"note: generator skipped on {LEVEL}" in text
    assert "experiments main, trigger;" in text and "6 runs (6 cluster runs, 0 generator runs)" in text
    assert not out.exists()


def test_the_report_of_a_level_needs_no_held_out_evaluations(tmp_path):
    from higher_dist.reproduce.claims import claims, write_results
    from higher_dist.reproduce.figures import draw_all

    plan = plan_mod.merge_and_write(plan_mod.build_plan(tmp_path / "p", ["main", "trigger"], 1, 1000, LEVEL,
                                                        "default", 1))
    finals = {"dqn-s0": 0.1, "her-s0": 0.5, "higher-s0": 0.45, "higher-trigger0-s0": 0.4,
              "higher-trigger1000-s0": 0.42, "higher-trigger2000-s0": 0.38}
    for run in plan.runs:  # what a run on a level records: training-goal evaluations only
        path = plan.path(run)
        path.mkdir(parents=True)
        (path / "config.json").write_text(json.dumps({"preset": run.preset, "seed": run.seed, "world": {"name": LEVEL}}))
        # an evaluation in each record, the last three at the run's final value (its end point is their mean)
        rows = [{"time": t, "frames": 100 * t, "success_rate_train": 0.1, "eval_frames": 100 * t,
                 "success_rate_eval_train": finals[run.name] * min(t, 8) / 8, "replay_success": 5,
                 "replay_timeout": 50} for t in range(1, 11)]
        (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    figures = draw_all(plan)
    assert {"success_train", "trigger", "replay_composition"} <= set(figures) and "success_heldout" not in figures
    rows = {row["claim"]: row for row in claims(plan)}
    assert not [c for c in rows if "noise" in c or "reward" in c or "expert pairs" in c]
    assert rows["DQN+HIGhER nearly matches DQN+HER"]["verdict"] == "holds"  # 45% against 50%
    assert rows["The trigger point (0, 1000, 2000 pairs) makes no difference"]["verdict"] == "holds"
    results = write_results(plan, figures).read_text()
    assert "| method | greedy success, the level's missions |" in results
    assert "| DQN+HER | 50.0% +- 0.0 (1 seed, 1,000 frames) |" in results
    assert "held-out goals |" not in results and "is a BabyAI level" in results
    # the machine and the runs' own pace: 100 frames a second in these metrics, six runs
    assert "6 cluster runs, 1 at a time, ran at 100-100 env frames/s each" in results and " cores (" in results
