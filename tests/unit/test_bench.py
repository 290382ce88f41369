"""`higher-bench`: its dispatcher and the contract every benchmark keeps (last line = one JSON object).
Speed itself is never asserted: figures are printed, not tested."""
import json

import pytest

from higher_dist.bench import COMMANDS, main


def number(cell: str) -> float:
    return float(cell.replace(",", "").removesuffix("/s"))


def test_world_bench_prints_a_row_per_batch_size_and_the_same_figures_as_json(capsys):
    assert main(["world", "--seconds", "0.05", "--no-minigrid"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    last = json.loads(lines[-1])
    assert lines[0] == "World steps/s, random actions, 0.05 s per row (world: paper)"
    assert lines[1].split() == ["environment", "batch", "steps/s", "x", "MiniGrid"]
    assert last["world"] == "paper" and last["seconds"] == 0.05
    rows = [line.removeprefix("higher_dist BatchedFetchAttr").split() for line in lines
            if line.startswith("higher_dist BatchedFetchAttr")]
    assert [int(batch) for batch, _, _ in rows] == [1, 64, 256]
    for batch, rate, ratio in rows:
        figure = last[f"b{batch}_steps_per_s"]
        # The row shows whole steps/s, the JSON a tenth: the same measurement.
        assert abs(number(rate) - figure) <= 1 and ratio == "n/a"
        # env steps (batch steps x batch size) per second: more than none, fewer than a core could ever do
        assert 0 < figure < 1e9
    assert lines[-2].split() == ["minigrid", "MiniGrid-Fetch-8x8-N3-v0", "unavailable"]
    assert last["minigrid_steps_per_s"] is None and last["ratio_b64"] is None


def test_unknown_benchmark_is_refused_with_the_known_names(capsys):
    assert main(["nope"]) == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and all(name in err for name in COMMANDS)


def test_time_to_success_needs_the_mean_of_three_evaluations_at_the_level():
    from higher_dist.bench.time_to_success_bench import crossings

    records = [{"frames": 1000, "elapsed_s": 10.0},  # no evaluation yet
               {"frames": 25_000, "elapsed_s": 30.0, "success_rate_eval_train": 0.05},
               {"frames": 30_000, "eval_frames": 25_000, "elapsed_s": 35.0,
                "success_rate_eval_train": 0.05},  # the same evaluation again
               {"frames": 50_000, "elapsed_s": 50.0, "success_rate_eval_train": 0.65},  # one lucky evaluation
               {"frames": 75_000, "elapsed_s": 70.0, "success_rate_eval_train": 0.35},
               {"frames": 100_000, "elapsed_s": 90.0, "success_rate_eval_train": 0.44},
               {"frames": 125_000, "elapsed_s": 110.0, "success_rate_eval_train": 0.70}]
    found = crossings(records, [0.2, 0.4, 0.5, 0.8])
    # Means: (0.05, 0.65, 0.35) = 0.35 at 75k; (0.65, 0.35, 0.44) = 0.48 at 100k; (0.35, 0.44, 0.70) = 0.497.
    assert found[0.2] == {"frames": 75_000, "seconds": 70.0, "success": 0.35}
    assert found[0.4] == {"frames": 100_000, "seconds": 90.0, "success": 0.48}
    assert 0.5 not in found and 0.8 not in found


def test_time_to_success_counts_each_evaluation_once_by_its_frames():
    from higher_dist.bench.time_to_success_bench import evaluations

    records = [{"frames": 60_000, "eval_frames": 50_000, "elapsed_s": 20.0, "success_rate_eval_train": 0.5},
               {"frames": 70_000, "eval_frames": 50_000, "elapsed_s": 25.0, "success_rate_eval_train": 0.5}]
    assert evaluations(records) == [{"frames": 50_000, "success": 0.5, "seconds": 20.0}]


def test_time_to_success_refuses_a_target_outside_0_1(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["time-to-success", "--targets", "40"])
    assert "--targets" in capsys.readouterr().err


def test_learner_bench_prints_consistent_figures_for_its_row(capsys):
    assert main(["learner", "--only", "prefetch", "--batch-sizes", "8,16", "--seconds", "0.05", "--repeat", "3"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    last = json.loads(lines[-1])
    assert lines[0].startswith("learner bench: 1 thread(s), torch ")
    assert lines[0].endswith("parameters, full prioritized replay, median of 3 interleaved round(s) of 0.05 s")
    assert lines[1].split() == ["samples/s", "(wall)", "B=8", "B=16", "cpu", "samples/s", "at", "B=8/16"]
    assert last["threads"] == 1 and last["repeat"] == 3 and list(last["rows"]) == ["+ prefetch"]
    printed = lines[2].removeprefix("+ prefetch").split()
    for b, cell, cpu in zip((8, 16), printed[:2], printed[2].split("/")):
        row = last["rows"]["+ prefetch"][f"b{b}"]
        # The table shows the JSON's figures: wall samples/s, then cpu samples/s.
        assert number(cell) == row["samples_per_s"] == last[f"b{b}_samples_per_s"]
        assert number(cpu) == row["cpu_samples_per_s"] == last[f"b{b}_cpu_samples_per_s"] > 0
        # Each update learns from one batch: samples/s = B x updates/s, within the rounding of each.
        assert abs(row["samples_per_s"] - b * last[f"b{b}_updates_per_s"]) <= 0.5 + b * 0.05
        assert abs(row["samples_per_s"] - b * row["updates_per_s"]) <= 0.5 + b * 0.5
        # The figure is the median of the three rounds (each round rounded alike).
        assert len(row["runs"]) == 3 and sorted(row["runs"])[1] == row["samples_per_s"]
        assert row["compile_s"] is None and 0 < row["samples_per_s"] < 1e8


def test_gpu_bench_refuses_a_host_without_cuda_and_measures_the_cpu_path_when_allowed(capsys):
    import torch

    if torch.cuda.is_available():
        import pytest

        pytest.skip("this host has a CUDA device: the refusal and the CPU fallback are for hosts without one")
    assert main(["gpu", "--cluster-seconds", "0"]) == 2
    assert "no CUDA device" in capsys.readouterr().out
    assert main(["gpu", "--allow-cpu", "--batch-sizes", "8", "--seconds", "0.05", "--no-compile",
                 "--cluster-seconds", "0"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["device"] == "cpu" and last["layout"]["learner_device"] == "cpu"
    assert last["learner"]["eager b8"]["samples_per_s"] > 0 and "cluster" not in last


def test_checkpoint_bench_writes_a_real_checkpoint_of_a_full_replay(capsys, tmp_path):
    assert main(["checkpoint", "--capacity", "10000", "--repeat", "1", "--dir", str(tmp_path)]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["capacity"] == 10_000 and 9_000 <= last["transitions"] <= 10_000  # full: a slot per frame, one more frame than steps per episode
    # The replay is most of the checkpoint: 7x7x4 bytes per frame slot, far above the networks alone.
    assert last["size_mib"] > 10_000 * 196 / 2**20 > last["size_without_replay_mib"]
    assert last["pause_s"] >= last["write_s"] > 0 and last["resume_load_s"] > 0
    assert list(tmp_path.iterdir()) == []  # its temp folder is removed


def test_generator_bench_measures_the_generator_higher_runs_on_that_world(capsys, monkeypatch):
    from higher_dist.bench import generator_bench
    from higher_dist.config_presets import make_config

    seen = []
    real = generator_bench.measure_generator

    def recording(*args, **kwargs):
        seen.append(kwargs["cfg"])
        return real(*args, **kwargs)

    monkeypatch.setattr(generator_bench, "measure_generator", recording)
    assert main(["generator", "--pairs", "16", "--steps", "2", "--eval-pairs", "16", "--world", "paper"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["pairs"] == 16 and last["steps"] == 2 and 0 <= last["seen_exact_match"] <= 1
    assert seen == [make_config("higher", "paper").generator]


def test_generator_bench_measures_a_variant_set_on_the_command_line(capsys, monkeypatch):
    from higher_dist.bench import generator_bench

    seen = []
    real = generator_bench.measure_generator
    monkeypatch.setattr(generator_bench, "measure_generator",
                        lambda *args, **kwargs: (seen.append(kwargs["cfg"]), real(*args, **kwargs))[1])
    small = ["generator", "--pairs", "16", "--steps", "2", "--eval-pairs", "16"]
    assert main(small + ["--set", "generator.beam_width=8", "--set", "generator.lr=0.01"]) == 0
    assert seen[-1].beam_width == 8 and seen[-1].lr == 0.01
    for bad, named in (("dqn.lr=0.1", "dqn.lr"), ("generator.beam_width=-1", "generator.beam_width"),
                       ("generator.no_such_field=1", "generator.no_such_field")):
        with pytest.raises(SystemExit) as stop:
            main(small + ["--set", bad])
        assert stop.value.code == 2 and named in capsys.readouterr().err
    assert len(seen) == 1  # nothing refused was measured
