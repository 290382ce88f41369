"""higher-plot on run directories written by the test."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from higher_dist.analysis.runs import find_runs, mean_band, success_key
from higher_dist.plot import generator_figure, main, replay_figure, success_figure

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


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def curve(path: Path, key: str) -> tuple[np.ndarray, np.ndarray]:
    """(frames, values) of the records of metrics.jsonl that carry `key`, read back with json."""
    records = [json.loads(line) for line in (path / "metrics.jsonl").read_text().splitlines()[:-1]]  # not the torn one
    pts = [(r["frames"], r[key]) for r in records if r.get(key) is not None]
    return np.array([f for f, _ in pts], dtype=float), np.array([v for _, v in pts], dtype=float)


def three_runs(tmp_path: Path) -> list[Path]:
    return [write_run(tmp_path / "higher_s0", "higher", 0), write_run(tmp_path / "higher_s1", "higher", 1),
            write_run(tmp_path / "dqn_s0", "dqn", 0, generator=False)]


def test_plot_writes_each_figure_it_prints(tmp_path, capsys):
    out = tmp_path / "plots"
    assert main([str(r) for r in three_runs(tmp_path)] + ["--out", str(out)]) == 0
    printed = capsys.readouterr().out.split()
    names = ["success_rate.png", "success_rate_heldout.png", "generator_accuracy.png", "replay_composition.png"]
    assert printed == [str(out / name) for name in names]
    assert sorted(p.name for p in out.iterdir()) == sorted(names)
    width, height = png_size(out / "success_rate.png")  # 8 x 5 inches at 110 dpi, trimmed to its content
    assert 700 < width <= 880 and 450 < height <= 560


def test_success_figure_draws_one_run_as_is_and_seeds_as_their_mean_and_band(tmp_path):
    paths = three_runs(tmp_path)
    fig = success_figure(find_runs([str(p) for p in paths]), success_key, "Greedy success on training goals")
    ax = fig.axes[0]
    assert (ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) == ("Greedy success on training goals",
                                                                 "environment frames", "success rate")
    assert ax.get_ylim() == (-0.02, 1.02)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["dqn", "higher (mean of 2 seeds)"]
    lines = {line.get_label(): line for line in ax.get_lines()}
    # One seed: its greedy evaluations, records 3..19, as recorded.
    x, y = curve(paths[2], "success_rate_eval_train")
    assert len(x) == 17
    np.testing.assert_array_equal(lines["dqn"].get_xdata(), x)
    np.testing.assert_array_equal(lines["dqn"].get_ydata(), y)
    # Two seeds: both interpolated onto 200 points over the frames both cover, their mean drawn ...
    (x0, y0), (x1, y1) = curve(paths[0], "success_rate_eval_train"), curve(paths[1], "success_rate_eval_train")
    grid = np.linspace(max(x0[0], x1[0]), min(x0[-1], x1[-1]), 200)
    at0, at1 = np.interp(grid, x0, y0), np.interp(grid, x1, y1)
    mean = lines["higher (mean of 2 seeds)"]
    np.testing.assert_allclose(mean.get_xdata(), grid)
    np.testing.assert_allclose(mean.get_ydata(), (at0 + at1) / 2)
    # ... within a band from the lower seed to the higher one.
    (band,) = ax.collections
    edge = band.get_paths()[0].vertices
    assert edge[:, 0].min() == pytest.approx(grid[0]) and edge[:, 0].max() == pytest.approx(grid[-1])
    assert edge[:, 1].min() == pytest.approx(np.minimum(at0, at1).min())
    assert edge[:, 1].max() == pytest.approx(np.maximum(at0, at1).max())


def test_generator_figure_draws_validation_solid_and_relabel_accuracy_dashed(tmp_path):
    paths = three_runs(tmp_path)[:2]
    ax = generator_figure(find_runs([str(p) for p in paths])).axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert sorted(lines) == ["higher seed 0: relabel accuracy", "higher seed 0: validation accuracy",
                             "higher seed 1: relabel accuracy", "higher seed 1: validation accuracy"]
    for seed, path in enumerate(paths):
        for what, key, style in (("validation", "generator_val_accuracy", "-"),
                                 ("relabel", "relabel_accuracy", "--")):
            line = lines[f"higher seed {seed}: {what} accuracy"]
            x, y = curve(path, key)
            np.testing.assert_array_equal(line.get_xdata(), x)
            np.testing.assert_array_equal(line.get_ydata(), y)
            assert line.get_linestyle() == style
    assert ax.get_ylabel() == "exact-match accuracy"


def test_replay_figure_stacks_each_origins_share_per_run(tmp_path):
    paths = three_runs(tmp_path)
    fig = replay_figure(find_runs([str(p) for p in paths]))
    panels = [ax for ax in fig.axes if ax.axison]
    assert [ax.get_title() for ax in panels] == ["higher seed 0", "higher seed 1", "dqn seed 0"]
    assert [c.get_label() for c in panels[0].collections] == ["success", "wrong pick", "time-out", "relabelled"]
    # The bottom layer's top edge is the success share: 10 i of 10 i + 30 i + 50 + 20 i, at record i's frames.
    frames, _ = curve(paths[0], "replay_success")
    top = {}
    for vx, vy in panels[0].collections[0].get_paths()[0].vertices:
        top[vx] = max(top.get(vx, 0.0), vy)
    assert [top[f] for f in frames] == pytest.approx([10 * i / (60 * i + 50) for i in range(20)])
    # The top layer's top edge is the whole replay, at every frame.
    assert max(panels[0].collections[-1].get_paths()[0].vertices[:, 1]) == pytest.approx(1.0)
    assert panels[2].collections[-1].get_label() == "relabelled"  # drawn, at zero, for a run without relabels


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
    assert rows[-1]["cycling_train"] == ""  # these records predate the cycling share: an empty cell, not a 0
    printed = capsys.readouterr().out
    assert "| frames | minutes |" in printed and printed.count("\n| ") >= 18
