"""`higher-bench`: its dispatcher and the contract every benchmark keeps (last line = one JSON object).
Speed itself is never asserted: figures are printed, not tested."""
import json

from higher_dist.bench import COMMANDS, main


def test_world_bench_ends_with_its_figures_as_json(capsys):
    assert main(["world", "--seconds", "0.05", "--no-minigrid"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("b1_steps_per_s", "b64_steps_per_s", "b256_steps_per_s", "minigrid_steps_per_s", "ratio_b64"):
        assert key in last
    assert last["b64_steps_per_s"] > 0 and last["minigrid_steps_per_s"] is None


def test_unknown_benchmark_is_refused_with_the_known_names(capsys):
    assert main(["nope"]) == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and all(name in err for name in COMMANDS)


def test_time_to_success_finds_the_first_evaluation_at_each_level():
    from higher_dist.bench.time_to_success_bench import crossings

    records = [{"frames": 1000, "time": 110.0},  # no evaluation yet
               {"frames": 25_000, "time": 130.0, "success_rate_eval_train": 0.05},
               {"frames": 50_000, "time": 150.0, "success_rate_eval_train": 0.25},
               {"frames": 75_000, "time": 170.0, "success_rate_eval_train": 0.15},
               {"frames": 100_000, "time": 190.0, "success_rate_eval_train": 0.41}]
    found = crossings(records, [0.1, 0.2, 0.4, 0.5], launched=100.0)
    assert found[0.1] == {"frames": 50_000, "seconds": 50.0, "success": 0.25}
    assert found[0.2]["frames"] == 50_000  # one evaluation can cross two levels
    assert found[0.4] == {"frames": 100_000, "seconds": 90.0, "success": 0.41}
    assert 0.5 not in found


def test_time_to_success_refuses_a_target_outside_0_1(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["time-to-success", "--target", "40"])
    assert "--target" in capsys.readouterr().err


def test_time_to_success_uses_the_frames_the_evaluated_weights_had_seen():
    from higher_dist.bench.time_to_success_bench import crossings

    found = crossings([{"frames": 60_000, "eval_frames": 50_000, "time": 20.0, "success_rate_eval_train": 0.5}],
                      [0.4], launched=0.0)
    assert found[0.4]["frames"] == 50_000


def test_learner_bench_measures_one_lever_row_through_the_replay(capsys):
    assert main(["learner", "--only", "prefetch", "--batch-sizes", "8", "--seconds", "0.05"]) == 0
    out = capsys.readouterr().out
    last = json.loads(out.strip().splitlines()[-1])
    row = last["rows"]["+ prefetch"]["b8"]
    assert row["samples_per_s"] > 0 and row["cpu_samples_per_s"] > 0 and row["compile_s"] is None
    assert last["b8_samples_per_s"] == row["samples_per_s"] and "+ prefetch" in out
