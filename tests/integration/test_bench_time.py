"""`higher-bench time-to-success` end to end on the small world: a real cluster, stopped by its frame
cap (an unreachable target), reporting what it saw as its last-line JSON."""
import json
import subprocess
import sys


def test_time_to_success_runs_the_cluster_to_its_frame_cap(tmp_path):
    cmd = [sys.executable, "-c", "import sys; from higher_dist.bench import main; sys.exit(main(sys.argv[1:]))",
           "time-to-success", "--preset", "her", "--world", "small", "--targets", "0.99", "1.0", "--frames-cap", "6000",
           "--max-minutes", "4", "--eval-every", "2000", "--eval-episodes", "8", "--",
           "--actors", "1", "--envs-per-actor", "8", "--set", "replay.min_size=200", "--set", "dqn.batch_size=16"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["targets"] == [0.99, 1.0] and len(result["runs"]) == 1
    run = result["runs"][0]
    assert run["stop"] == "frames cap", run
    assert run["frames"] >= 6000 and run["seconds"] > 0 and run["frames_per_s"] > 0
    assert run["evaluations"] >= 1 and 0.0 <= run["best_eval"] <= 1.0
    assert set(run["levels"]) == {"online", "averaged"} and set(run["levels"]["online"]) == {"0.99", "1"}
    assert run["batch_size"] == 16 and run["layout"] and "learner" in run["layout"]
