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
