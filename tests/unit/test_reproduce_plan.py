"""The reproduce plan: which runs, shared between experiments, with which flags; plan.json merging; run
states on disk; the cost estimate's frame rate; metrics trimmed to a checkpoint before a resume."""
from __future__ import annotations

import json

import pytest

from higher_dist.config import ConfigError
from higher_dist.reproduce import plan as plan_mod
from higher_dist.reproduce.claims import random_success
from higher_dist.reproduce.executor import trim_metrics_to_checkpoint
from higher_dist.reproduce.status import estimate, measured_fps, run_state
from higher_dist.rundir import RunDir


def build(tmp_path, experiments=("main", "noise"), seeds=2, **kw):
    kw.setdefault("frames", 100_000)
    return plan_mod.build_plan(tmp_path / "p", list(experiments), seeds, world="small", profile=kw.pop("profile", "paper"),
                               parallel=1, **kw)


def test_experiments_share_runs_and_run_seed_major(tmp_path):
    plan = build(tmp_path)
    names = [r.name for r in plan.runs]
    assert len(names) == len(set(names)) == 2 * 7  # main 4 + noise 3 new per seed (her and dqn shared)
    her = next(r for r in plan.runs if r.name == "her-s0")
    assert her.experiments == ("main", "noise")
    assert names.index("noisy-her-p0.8-s0") < names.index("dqn-s1")  # every first seed before any second
    assert plan.experiments["noise"][0] == "her-s0" and "dqn-s0" in plan.experiments["noise"]
    noisy = next(r for r in plan.runs if r.name == "noisy-her-p0.5-s1")
    assert noisy.preset == "noisy-her" and "relabel.noise_p=0.5" in noisy.flags and noisy.seed == 1


def test_methods_filter_and_bad_names_are_refused(tmp_path):
    plan = build(tmp_path, ("main",), seeds=1, methods=["dqn", "her"])
    assert [r.name for r in plan.runs] == ["dqn-s0", "her-s0"]
    with pytest.raises(ConfigError, match="selects no run"):
        build(tmp_path, ("main",), methods=["nope"])
    with pytest.raises(ConfigError, match="unknown"):
        build(tmp_path, ("mian",))


def test_profile_reaches_every_run_as_the_cluster_flag(tmp_path):
    assert plan_mod.profile_flags("paper") == ("--profile", "paper")
    assert plan_mod.profile_flags("default") == ()
    with pytest.raises(ConfigError, match="--profile"):
        plan_mod.profile_flags("fast")
    plan = build(tmp_path, ("main", "trigger"), seeds=1)
    configs = plan_mod.check_configs(plan)
    her, trigger0 = configs["her-s0"], configs["higher-trigger0-s0"]
    assert her.profile == "paper" and her.exploration.kind == "linear" and her.exploration.decay_frames == 100_000
    assert trigger0.generator.n_min == 0 and trigger0.generator.min_accuracy == 0  # the run's own flags win
    assert configs["dqn-s0"].eval.every_frames == 10_000  # 100k frames: ten evaluations (the small world's own)
    short = plan_mod.check_configs(build(tmp_path, ("main",), seeds=1, frames=6000))
    assert short["dqn-s0"].eval.every_frames == 600


def test_paper_world_higher_keeps_failures_out_on_main_but_not_in_the_trigger_runs(tmp_path):
    plan = plan_mod.build_plan(tmp_path / "p", ["main", "trigger"], 1, world="paper", profile="default",
                               parallel=1, frames=100_000)
    configs = plan_mod.check_configs(plan)
    assert configs["higher-s0"].relabel.withheld_while_gated  # the paper world's default for HIGhER
    # The trigger runs store every failure until their generator starts, as the paper's do.
    assert not [n for n, c in configs.items() if "trigger" in n and c.relabel.withheld_while_gated]
    assert len([n for n in configs if "trigger" in n]) == len(plan_mod.TRIGGER_PAIRS)


def test_a_flag_that_restates_a_runs_saved_config_leaves_it_the_same_run(tmp_path):
    from dataclasses import replace

    def plan_again():
        return plan_mod.build_plan(tmp_path / "p", ["trigger"], 1, world="small", profile="default",
                                   parallel=1, frames=100_000)

    plan = plan_again()
    plan_mod.merge_and_write(plan)
    name = "higher-trigger1000-s0"
    run = next(r for r in plan.runs if r.name == name)
    # An earlier plan gave the run fewer flags (a default was made explicit since).
    recorded = json.loads((tmp_path / "p" / "plan.json").read_text())
    recorded["runs"][name]["flags"] = [f for f in recorded["runs"][name]["flags"] if "withheld" not in f]
    (tmp_path / "p" / "plan.json").write_text(json.dumps(recorded))
    with pytest.raises(ConfigError, match="other settings"):  # nothing on disk says what the run was
        plan_mod.merge_and_write(plan_again())
    cfg = plan_mod.check_configs(plan)[name]
    RunDir(str(plan.path(run))).write_config(replace(cfg, frames=50_000, actors=2))  # a resume may change these
    merged = plan_mod.merge_and_write(plan_again())  # the saved config is what the flags give: the same run
    assert "relabel.withheld_while_gated=false" in next(r for r in merged.runs if r.name == name).flags
    # A saved config that differs in what is learned is another experiment, refused by name.
    (tmp_path / "p" / "plan.json").write_text(json.dumps(recorded))
    RunDir(str(plan.path(run))).write_config(replace(cfg, relabel=replace(cfg.relabel, withheld_while_gated=True)))
    with pytest.raises(ConfigError, match=name):
        plan_mod.merge_and_write(plan_again())


def test_bad_overrides_are_refused_before_anything_runs(tmp_path):
    plan = build(tmp_path, ("main",), seeds=1, sets=["dqn.lr=fast"])
    with pytest.raises(ConfigError, match="dqn.lr"):
        plan_mod.check_configs(plan)


def test_plan_json_keeps_earlier_runs_and_refuses_changed_ones(tmp_path):
    first = build(tmp_path, ("main",), seeds=1, methods=["her"])
    plan_mod.merge_and_write(first)
    longer = build(tmp_path, ("noise",), seeds=1, frames=200_000, actors=3)
    recorded = plan_mod.merge_and_write(longer)
    data = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert data["runs"]["her-s0"]["frames"] == 200_000  # a longer budget extends the run
    assert data["runs"]["her-s0"]["actors"] == first.runs[0].actors  # its exploration ladder stays
    assert data["runs"]["her-s0"]["experiments"] == ["main", "noise"]
    assert {r.name for r in recorded.runs} >= {"her-s0", "noisy-her-p0.2-s0", "dqn-s0"}
    changed = build(tmp_path, ("main",), seeds=1, methods=["her"], sets=["dqn.lr=0.01"])
    with pytest.raises(ConfigError, match="her-s0 was planned there with other settings"):
        plan_mod.merge_and_write(changed)
    assert plan_mod.read_plan(tmp_path / "p").experiments["noise"][0] == "her-s0"


def test_plan_json_names_every_command_and_machine_and_the_report_every_budget(tmp_path):
    from higher_dist.reproduce.claims import budgets

    for experiments, frames, command, host in ((("main",), 200_000, ["higher-reproduce", "main"], "box A"),
                                                (("trigger",), 100_000, ["higher-reproduce", "trigger"], "box B"),
                                                (("main",), 200_000, ["higher-reproduce", "main"], "box A")):
        plan = build(tmp_path, experiments, seeds=2, frames=frames, command=command)
        plan.settings["machine"] = host
        recorded = plan_mod.merge_and_write(plan)
    settings = plan_mod.read_plan(tmp_path / "p").settings
    assert settings["commands"] == [["higher-reproduce", "main"], ["higher-reproduce", "trigger"]]
    assert settings["machines"] == ["box A", "box B"]
    assert budgets(recorded) == "main: 2 seeds x 200,000 frames; trigger: 2 seeds x 100,000 frames"


def _metrics(path, rows):
    path.mkdir(parents=True, exist_ok=True)
    (path / "metrics.jsonl").write_text("".join(json.dumps({"time": t, "frames": f}) + "\n" for t, f in rows))


def test_run_states_and_measured_frame_rate(tmp_path):
    plan = build(tmp_path, ("main",), seeds=1, methods=["dqn"], frames=1000)
    run = plan.runs[0]
    path = plan.path(run)
    assert run_state(run, path) == "pending"
    path.mkdir(parents=True)
    assert run_state(run, path) == "stale"
    RunDir(path).save_checkpoint("learner", {"core": {"counters": {"frames": 400}}})
    _metrics(path, [(0, 0), (5, 200), (10, 400), (100, 400), (105, 600)])  # a stop between 10 s and 100 s
    assert run_state(run, path) == "resumable"
    assert measured_fps(path) == pytest.approx(600 / 15)  # the 90 s gap is not running time
    rows, wall, rates = estimate(plan, plan.runs, {}, parallel=1)
    assert rates.source.startswith("measured: median of 1 run(s)") and rates.fps == pytest.approx(40)
    assert rows[0]["left"] == 400 and wall == pytest.approx(400 / 40)
    assert trim_metrics_to_checkpoint(path) == 400
    assert [r["frames"] for r in map(json.loads, (path / "metrics.jsonl").read_text().splitlines())] == [0, 200, 400, 400]
    _metrics(path, [(0, 0), (5, 1000)])
    assert run_state(run, path) == "done"


def test_fallback_rate_names_its_source(tmp_path):
    plan = build(tmp_path, ("main",), seeds=1, methods=["dqn"])
    _, wall, rates = estimate(plan, plan.runs, {"dqn-s0": 16.0}, parallel=1, bench_dir=tmp_path / "none")
    assert "not measured here" in rates.source and "docs/benchmarks.md" in rates.source
    assert wall == pytest.approx(100_000 / (rates.fps / 4))  # 4x the samples per insert: a quarter of the rate


def test_random_policy_success_is_measured_one_episode_per_env():
    rate = random_success("small", envs=500)
    assert 0.02 < rate < 0.5


def test_higher_plot_on_a_plan_folder_draws_the_plans_figures_and_table(tmp_path):
    from higher_dist.cli import plot_main  # the higher-plot command

    plan = build(tmp_path, ("main",), seeds=2, methods=["dqn"], frames=1000)
    plan_mod.merge_and_write(plan)
    for seed, level in ((0, 0.2), (1, 0.4)):
        path = plan.path(plan.runs[seed])
        path.mkdir(parents=True)
        (path / "config.json").write_text(json.dumps({"preset": "dqn", "seed": seed, "world": {"name": "small"}}))
        # an evaluation in each record, the last three at `level` (a run's end point is their mean)
        rows = [{"time": t, "frames": 100 * t, "success_rate_train": 0.1, "eval_frames": 100 * t,
                 "success_rate_eval_train": level * min(t, 8) / 8, "success_rate_eval_heldout": level / 2,
                 "replay_success": 10, "replay_timeout": 90 + t} for t in range(1, 11)]
        (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert plot_main([str(plan.out)]) == 0
    assert (plan.out / "figures" / "success_train.png").stat().st_size > 5_000
    results = (plan.out / "results.md").read_text()
    # The last evaluations are 0.2 and 0.4: mean 30.0%, std 10.0 over the two seeds.
    assert "| DQN | 30.0% +- 10.0 (2 seeds, 1,000 frames) | 15.0% +- 5.0 (2 seeds, 1,000 frames) |" in results


def test_a_generator_run_writes_its_exact_match_and_the_figure_draws_it(tmp_path):
    from higher_dist.reproduce import gen_task
    from higher_dist.reproduce.figures import draw_all

    plan = build(tmp_path, ("generator",), seeds=1, methods=["gen-pairs1000"], generator_steps=20)
    plan_mod.merge_and_write(plan)
    run = plan.runs[0]
    assert run_state(run, plan.path(run)) == "pending"
    # The executor's argv, run in this process: 200 pairs instead of 1000 keep it quick.
    assert gen_task.main(["--pairs", "200", "--steps", str(run.steps), "--seed", "0", "--world", "small",
                          "--eval-pairs", "64", "--out", str(plan.path(run)), "--", *run.flags]) == 0
    result = json.loads((plan.path(run) / "result.json").read_text())
    assert result["pairs"] == 200 and 0.0 <= result["seen_exact_match"] <= 1.0 and 0.0 <= result["unseen_exact_match"] <= 1.0
    assert run_state(run, plan.path(run)) == "done"
    assert draw_all(plan_mod.read_plan(plan.out))["generator_pairs"].stat().st_size > 5_000


def test_the_generator_table_and_the_expert_pairs_verdict_read_every_seed(tmp_path):
    import numpy as np

    from higher_dist.reproduce.claims import claims, generator_table

    plan = plan_mod.merge_and_write(build(tmp_path, ("generator",), seeds=2, generator_steps=30, profile="default"))
    exact = {(1000, 0): (0.5, 0.4), (1000, 1): (0.7, 0.5), (5000, 0): (0.9, 0.8), (5000, 1): (0.7, 0.6)}
    for run in plan.runs:
        seen, unseen = exact.get((run.pairs, run.seed), (0.6, 0.6))
        plan.path(run).mkdir(parents=True)
        (plan.path(run) / "result.json").write_text(json.dumps(
            {"pairs": run.pairs, "steps": run.steps, "seed": run.seed, "seen_exact_match": seen,
             "unseen_exact_match": unseen}))
    table = generator_table(plan)
    assert table[2] == "| 1,000 | 2 | 30 | 60.0% +- 10.0 | 45.0% +- 5.0 |"
    assert table[-1] == f"| 5,000 | 2 | 30 | 80.0% +- 10.0 | 70.0% +- {100 * np.std([0.8, 0.6]):.1f} |"
    row = {r["claim"]: r for r in claims(plan)}["Generator from 5000 expert pairs: about 70% exact match"]
    assert row["verdict"] == "holds" and "unseen 70.0%" in row["ours"] and "from 1000 pairs: unseen 45.0%" in row["ours"]
    assert "far above" not in row["why"]  # 70% on held-out goals is the paper's own figure


def test_a_second_reproduce_on_the_same_folder_is_refused(tmp_path):
    import subprocess
    import sys

    from higher_dist.reproduce.cli import _lock

    other = subprocess.Popen([sys.executable, "-c", "import time; print('up', flush=True); time.sleep(60)  "
                              "# higher-reproduce stand-in"], stdout=subprocess.PIPE, text=True)
    try:
        # Popen returns once exec has begun, before the kernel fills in the child's command line;
        # its first line of output says the stand-in is running under its own name
        assert other.stdout.readline().strip() == "up"
        (tmp_path / "reproduce.pid").write_text(str(other.pid))
        with pytest.raises(ConfigError, match=f"pid {other.pid}"):
            _lock(tmp_path)
    finally:
        other.kill()
        other.wait()
        other.stdout.close()
    _lock(tmp_path)  # its process is gone: the folder is free again, and now ours
    assert (tmp_path / "reproduce.pid").read_text() == str(__import__("os").getpid())


def _write_run(plan, name, final, frames=1000, generator=None, gate_from=None):
    run = next(r for r in plan.runs if r.name == name)
    path = plan.path(run)
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"preset": run.preset, "seed": run.seed, "world": {"name": "small"}}))
    # an evaluation in each record, the last three at `final` (a run's end point is their mean)
    rows = [{"time": t, "frames": frames * t // 10, "eval_frames": frames * t // 10,
             "success_rate_eval_train": final * min(t, 8) / 8,
             "success_rate_eval_heldout": final / 2, "replay_success": 5, "replay_timeout": 50,
             **({"generator_val_accuracy": generator * t / 10} if generator is not None else {}),
             **({"relabel_gate_open": frames * t // 10 >= gate_from} if gate_from is not None else {})}
            for t in range(1, 11)]
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_noise_and_trigger_figures_and_their_verdicts(tmp_path):
    from higher_dist.reproduce.claims import claims
    from higher_dist.reproduce.figures import draw_all

    plan = plan_mod.merge_and_write(build(tmp_path, ("main", "noise", "trigger"), seeds=1, frames=1000))
    finals = {"dqn-s0": 0.05, "her-s0": 0.5, "reward-s0": 0.42, "noisy-her-p0.2-s0": 0.45,
              "noisy-her-p0.5-s0": 0.3, "noisy-her-p0.8-s0": 0.2, "higher-trigger0-s0": 0.4,
              "higher-trigger1000-s0": 0.3, "higher-trigger2000-s0": 0.1}
    gates = {"higher-trigger0-s0": 100_000, "higher-trigger1000-s0": 600_000, "higher-trigger2000-s0": None}
    for name, final in finals.items():
        _write_run(plan, name, final, **({"frames": 1_000_000, "gate_from": gates[name]} if name in gates else {}))
    _write_run(plan, "higher-s0", 0.45, generator=0.8)
    figures = draw_all(plan)
    assert {"success_train", "noise", "noise_curves", "trigger", "generator_accuracy", "replay_composition"} <= set(figures)
    rows = {row["claim"]: row for row in claims(plan)}
    noise = rows["HER keeps 80% of its performance at 50% noise"]
    assert noise["verdict"] == "does not hold" and "ratio 0.60" in noise["why"]  # 0.3 / 0.5
    assert "6.2% of relabels are entirely right" in noise["why"]  # (1 - 0.5) ** 4
    assert rows["HER with 80% noise still beats DQN"]["verdict"] == "holds"
    trigger = rows["The trigger point (0, 1000, 2000 pairs) makes no difference"]
    assert trigger["verdict"] == "does not hold" and "spread 30.0 points" in trigger["why"]
    # Why: when each trigger's relabelling really began (the gate opening), or that it never did.
    assert ("relabelling started at 0 pairs: 100k frames; 1000 pairs: 600k frames; 2000 pairs: not by 1.00M frames"
            in trigger["why"])
    assert rows["DQN+HIGhER nearly matches DQN+HER"]["verdict"] == "holds"  # 45% against 50%
    assert rows["HIGhER's generator reaches 78% at 5M frames"]["verdict"] == "holds"
    assert "measured at 1,000 frames" in rows["DQN+reward reaches about 40%"]["why"]


def test_dqn_near_random_is_judged_per_seed(tmp_path):
    """A mean near random can hide one seed that learnt: the verdict says the seeds disagree."""
    from higher_dist.reproduce.claims import claims, random_success

    rnd = random_success("small")
    for finals, verdict in (((rnd, rnd + 0.02), "holds"), ((0.0, rnd + 0.08), "mixed"),
                            ((rnd + 0.2, rnd + 0.3), "does not hold")):
        out = tmp_path / verdict.replace(" ", "-")
        plan = plan_mod.merge_and_write(build(out, ("main",), seeds=2, frames=1000, methods=["dqn"]))
        for seed, final in enumerate(finals):
            _write_run(plan, f"dqn-s{seed}", final)
        row = next(r for r in claims(plan) if r["claim"] == "DQN stays near random")
        assert row["verdict"] == verdict, (finals, row)
        if verdict == "mixed":
            assert "seeds disagree" in row["why"] and f"{100 * (rnd + 0.08):.1f}%" in row["why"]


def test_noise_beating_dqn_needs_a_difference_beyond_the_seeds_spread(tmp_path):
    """A noisy HER a fraction of a point above DQN, where the seeds scatter by more, beats nothing: the
    verdict weighs the difference of the means against its standard error over seeds."""
    from higher_dist.reproduce.claims import claims

    for noisy, dqn, verdict in (((0.30, 0.32), (0.01, 0.03), "holds"), ((0.02, 0.06), (0.01, 0.05), "inconclusive"),
                                ((0.0, 0.01), (0.02, 0.03), "does not hold")):
        out = tmp_path / verdict.replace(" ", "-")
        plan = plan_mod.merge_and_write(build(out, ("main", "noise"), seeds=2, frames=1000,
                                              methods=["dqn", "noisy-her-p0.8"]))
        for seed in range(2):
            _write_run(plan, f"dqn-s{seed}", dqn[seed])
            _write_run(plan, f"noisy-her-p0.8-s{seed}", noisy[seed])
        row = next(r for r in claims(plan) if r["claim"] == "HER with 80% noise still beats DQN")
        assert row["verdict"] == verdict, (noisy, dqn, row)
        assert "2 standard errors" in row["why"]


def test_a_comparison_of_runs_at_different_budgets_says_so(tmp_path):
    """A trigger at 2000 pairs run on to 2M frames beside triggers stopped at 1M: the verdict's why says
    the end points are not at the same frame."""
    from higher_dist.reproduce.claims import claims

    plan = plan_mod.merge_and_write(build(tmp_path, ("trigger",), seeds=1, frames=1000))
    for name, final, frames in (("higher-trigger0-s0", 0.4, 1_000_000), ("higher-trigger1000-s0", 0.3, 1_000_000),
                                ("higher-trigger2000-s0", 0.35, 2_000_000)):
        _write_run(plan, name, final, frames=frames, gate_from=0)
    row = next(r for r in claims(plan) if r["claim"].startswith("The trigger point"))
    assert "reached 1,000,000 to 2,000,000 frames: their end points are not at the same frame" in row["why"]
    assert "2000 pairs: 0.35" not in row["ours"] and "(1 seed, 2,000,000 frames)" in row["ours"]


def test_print_config_prints_every_cluster_run_resolved_and_writes_nothing(tmp_path, capsys):
    from higher_dist.reproduce.cli import main as reproduce_main

    out = tmp_path / "plan"
    assert reproduce_main(["main", "--seeds", "2", "--frames", "100000", "--set", "dqn.lr=0.0007",
                           "--print-config", "--out", str(out)]) == 0
    configs = json.loads(capsys.readouterr().out)
    assert set(configs) == {f"{m}-s{s}" for m in ("dqn", "her", "higher", "reward") for s in (0, 1)}
    assert {c["seed"] for c in configs.values()} == {0, 1}
    assert all(c["frames"] == 100_000 and c["dqn"]["lr"] == 0.0007 for c in configs.values())
    assert configs["higher-s1"]["relabel"]["strategy"] == "learned" and configs["her-s0"]["relabel"]["strategy"] == "expert"
    assert not out.exists()  # nothing written, nothing run
