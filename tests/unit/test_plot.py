"""higher-plot on run directories written by the test."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from higher_dist.analysis.runs import mean_band
from higher_dist.plot import main

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def write_run(path: Path, preset: str, seed: int, n: int = 20, generator: bool = True) -> Path:
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"preset": preset, "seed": seed, "world": {"name": "fetch_attr"}}))
    rng = np.random.default_rng(seed)
    with open(path / "metrics.jsonl", "w") as f:
        for i in range(n):
            frames = 1000 * i + int(rng.integers(0, 300))  # seeds log at slightly different frames
            progress = i / (n - 1)
            record = {"time": 1.0e9 + 2 * i, "preset": preset, "frames": frames,
                      "success_rate_train": min(1.0, progress * (0.5 + 0.1 * seed)),
                      "success_rate_eval_train": None if i < 3 else progress * (0.7 + 0.1 * seed),
                      "success_rate_eval_heldout": None if i < 3 else progress * 0.6,
                      "replay_success": 10 * i, "replay_wrong_pick": 30 * i, "replay_timeout": 50,
                      "replay_relabelled": 20 * i if generator else 0}
            if generator:
                record["relabel_gate_open"] = i >= 6
                record["generator_val_accuracy"] = None if i < 5 else 0.5 + progress / 3
                record["relabel_accuracy"] = None if i < 8 else 0.7
            f.write(json.dumps(record) + "\n")
        f.write('{"frames": 99999, "torn')  # a crash mid-write leaves half a line: it is skipped
    return path


def test_plot_writes_pngs(tmp_path, capsys):
    runs = [write_run(tmp_path / "higher_s0", "higher", 0), write_run(tmp_path / "higher_s1", "higher", 1),
            write_run(tmp_path / "dqn_s0", "dqn", 0, generator=False)]
    out = tmp_path / "plots"
    assert main([str(r) for r in runs] + ["--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in ("success_rate.png", "success_rate_heldout.png", "generator_accuracy.png", "replay_composition.png"):
        png = out / name
        assert png.is_file() and png.stat().st_size > 1000, name
        assert png.read_bytes()[:8] == PNG_SIGNATURE
        assert str(png) in printed


def test_plot_expands_a_folder_of_runs_and_skips_missing_generator(tmp_path, capsys):
    write_run(tmp_path / "runs" / "a", "dqn", 0, generator=False)
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "success_rate.png").is_file()
    assert not (tmp_path / "o" / "generator_accuracy.png").exists()
    assert "skipped generator_accuracy.png" in capsys.readouterr().out


def test_plot_on_empty_directory_returns_2(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty), "--out", str(tmp_path / "o")]) == 2
    assert f"higher-plot: {empty} holds no run (no metrics.jsonl)" in capsys.readouterr().err
    (empty / "metrics.jsonl").write_text("")
    assert main([str(empty), "--out", str(tmp_path / "o")]) == 2
    assert "holds no run" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_mean_band_over_common_range():
    a = (np.array([0.0, 10.0]), np.array([0.0, 1.0]))
    b = (np.array([2.0, 8.0]), np.array([1.0, 1.0]))
    grid, mean, low, high = mean_band([a, b])
    assert grid[0] == 2.0 and grid[-1] == 8.0  # only where both seeds have data
    assert np.allclose(low, grid / 10) and np.allclose(high, 1.0) and np.allclose(mean, (grid / 10 + 1) / 2)
    assert mean_band([(np.array([0.0, 1.0]), np.zeros(2)), (np.array([2.0, 3.0]), np.zeros(2))]) is None


def test_table_has_one_row_per_new_evaluation_and_the_last_record(tmp_path, capsys):
    run = write_run(tmp_path / "higher_s0", "higher", 0, n=20)
    out = tmp_path / "o"
    assert main([str(run), "--out", str(out), "--table"]) == 0
    lines = (out / "higher_s0.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header[:5] == ["frames", "minutes", "updates_per_frame", "exploring_success", "greedy_train"]
    rows = [dict(zip(header, line.split(","))) for line in lines[1:]]
    # records 3..19 each carry a new evaluation; records 0-2 carry none and are not rows
    assert len(rows) == 17
    frames = [float(r["frames"]) for r in rows]
    assert frames == sorted(frames) and frames[0] >= 3000
    assert float(rows[-1]["greedy_train"]) == 0.7 and float(rows[-1]["greedy_heldout"]) == 0.6
    assert rows[0]["generator_val"] == "" and float(rows[-1]["generator_val"]) > 0.8
    assert [r["gate_open"] for r in rows[:4]] == ["0", "0", "0", "1"]
    printed = capsys.readouterr().out
    assert "| frames | minutes |" in printed and printed.count("\n| ") >= 18
