"""The replay's composition against the paper's figures, and a run's end point as the mean of its last
evaluations: numbers worked out by hand from synthetic metrics."""
from __future__ import annotations

import json

import pytest

from higher_dist.analysis.runs import Run
from higher_dist.reproduce import replay_claims
from higher_dist.reproduce.figures import final


def _run(tmp_path, rows, capacity=200_000, name="r"):
    path = tmp_path / name
    path.mkdir()
    (path / "config.json").write_text(json.dumps({"replay": {"capacity": capacity}}))
    return Run(path, "higher", 0, "paper", rows)


def _counts(frames, success, wrong, timeout, relabelled):
    return {"frames": frames, "replay_success": success, "replay_wrong_pick": wrong, "replay_timeout": timeout,
            "replay_relabelled": relabelled}


def test_measures_of_one_run_by_hand(tmp_path):
    rows = [_counts(0, 10, 20, 70, 0), _counts(100_000, 10, 30, 60, 0),  # start: negative 90%, then 90%
            _counts(500_000, 20, 20, 20, 40),  # the relabelled peak, 40%
            _counts(900_000, 50, 10, 20, 20), _counts(1_000_000, 70, 10, 10, 10)]  # the last 10%: 900k..1M
    got = replay_claims.run_measures(_run(tmp_path, rows))
    assert got["negative_start"] == pytest.approx(0.9)
    assert got["relabelled_peak"] == pytest.approx(0.4) and got["peak_frames"] == 500_000
    assert got["relabelled_end"] == pytest.approx(0.15) and got["positive_end"] == pytest.approx(0.6)
    # time-outs weighted by frames (trapezoids): 0.7..0.6 over 100k, 0.6..0.2 over 400k, 0.2 over 400k,
    # 0.2..0.1 over the last 100k
    expected = (0.65 * 100_000 + 0.4 * 400_000 + 0.2 * 400_000 + 0.15 * 100_000) / 1_000_000
    assert got["timeout_mean"] == pytest.approx(expected)


def test_measures_weigh_frames_not_records(tmp_path):
    """A run writes a record every 2 s: the first seconds (the learner compiling, few frames) hold dozens of
    records. The start's share weighs each stretch by the frames it spans."""
    slow_start = [_counts(f, 0, 0, 100, 0) for f in range(0, 1001, 20)]  # 51 records, all negative
    rows = slow_start + [_counts(50_000, 50, 0, 50, 0), _counts(100_000, 50, 0, 50, 0), _counts(1_000_000, 50, 0, 50, 0)]
    got = replay_claims.run_measures(_run(tmp_path, rows))
    expected = (1.0 * 1000 + 0.75 * 49_000 + 0.5 * 50_000) / 100_000  # trapezoids over 0..100k frames
    assert got["negative_start"] == pytest.approx(expected)


def test_the_claim_row_holds_when_every_share_is_close_and_names_each_that_is_not(tmp_path):
    paper_like = [_counts(0, 10, 20, 70, 0), _counts(400_000, 5, 0, 55, 40), _counts(1_790_000, 35, 0, 50, 15),
                  _counts(2_000_000, 60, 0, 25, 15)]
    row = replay_claims.claim_row([_run(tmp_path, paper_like, name="a"), _run(tmp_path, paper_like, name="b")],
                                  "DQN+HIGhER")
    assert row["verdict"] == "holds" and not row["why"], row
    assert "2 seeds, 2,000,000 frames" in row["ours"]

    no_relabels = [_counts(0, 5, 25, 70, 0), _counts(2_000_000, 10, 20, 70, 0)]
    row = replay_claims.claim_row([_run(tmp_path, no_relabels, capacity=123_456, name="c")], "DQN+HIGhER")
    assert row["verdict"] == "partly"
    assert "relabelled peak 0% is 40 points below" in row["why"] and "123,456 transitions" in row["why"]
    assert "positive end 10% is 50 points below" in row["why"]
    assert "negative start" not in row["why"]  # 95% is within 10 points of 90%
    assert replay_claims.claim_row([], "DQN+HIGhER")["ours"] == "not measured"


def test_the_table_has_the_paper_and_each_method_with_seeds_and_frames(tmp_path):
    rows = [_counts(0, 10, 20, 70, 0), _counts(1_000_000, 60, 5, 20, 15)]
    lines = replay_claims.table({"DQN+HIGhER": [_run(tmp_path, rows)], "empty": []})
    assert lines[0].count("|") == 4 and "DQN+HIGhER (1 seed, 1,000,000 frames)" in lines[0]
    assert lines[2].startswith("| negative at the start | 90% | 90% +- 0 |")


def test_a_runs_end_point_is_the_mean_of_its_last_three_evaluations():
    key = "success_rate_eval_train"
    rows = []
    for i, value in enumerate((0.1, 0.2, 0.5, 0.4, 0.3)):
        rows += [{"frames": 1000 * i + d, "eval_frames": 1000 * i, key: value} for d in (0, 300, 600)]
    run = Run(None, "her", 0, "paper", rows)
    assert final(run, key) == pytest.approx(0.4)  # (0.5 + 0.4 + 0.3) / 3
    # a series that is not an evaluation keeps its latest value
    run.records.append({"frames": 9000, "eval_frames": 4000, "generator_val_accuracy": 0.9})
    assert final(run, "generator_val_accuracy") == 0.9
    assert final(Run(None, "her", 0, "paper", [{"frames": 5, key: 0.7}]), key) == 0.7  # no eval_frames: latest
