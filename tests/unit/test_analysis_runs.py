"""Run.evaluations: each greedy evaluation once, the one rule the figures, the time-to-success bench and
higher-plot's table all read. The records are the cases their separate rules once disagreed on."""
from __future__ import annotations

from pathlib import Path

import pytest

from higher_dist.analysis.runs import Run
from higher_dist.bench.time_to_success_bench import evaluations as bench_evaluations
from higher_dist.plot import curve_rows
from higher_dist.reproduce.figures import final

TRAIN, HELDOUT = "success_rate_eval_train", "success_rate_eval_heldout"


def _run(records: list[dict]) -> Run:
    return Run(Path("r"), "her", 0, "paper", records)


# A cluster run killed after 3,200 frames and resumed from its checkpoint at 2,600: the records after the
# checkpoint are written again, and the evaluation at 3,000 frames runs again on the resumed weights.
RESUMED = [
    {"frames": 1000, "elapsed_s": 5.0},  # no evaluation yet
    {"frames": 2000, "elapsed_s": 10.0, "eval_frames": 1500, TRAIN: 0.1, HELDOUT: 0.05},
    {"frames": 2500, "elapsed_s": 12.0, "eval_frames": 1500, TRAIN: 0.1, HELDOUT: 0.05},  # repeated
    {"frames": 3000, "elapsed_s": 20.0, "eval_frames": 3000, TRAIN: 0.3, HELDOUT: 0.2},
    {"frames": 3200, "elapsed_s": 22.0, "eval_frames": 3000, TRAIN: 0.3, HELDOUT: 0.2},
    # resumed at 2,600 frames: no evaluation until the next one is due
    {"frames": 2700, "elapsed_s": 23.0},
    {"frames": 3100, "elapsed_s": 25.0, "eval_frames": 3000, TRAIN: 0.4, HELDOUT: 0.25},  # evaluated again
    {"frames": 3300, "elapsed_s": 26.0, "eval_frames": 3000, TRAIN: 0.4, HELDOUT: 0.25},
]


def test_an_evaluation_repeated_by_later_records_counts_once_at_its_first_record():
    evals = _run(RESUMED).evaluations()
    assert [e.frames for e in evals] == [1500, 3000]
    assert evals[0].record is RESUMED[1]  # its first record: elapsed_s 10, not 12


def test_an_evaluation_made_again_after_a_resume_replaces_the_earlier_one_at_its_frames():
    evals = _run(RESUMED).evaluations()
    assert [(e.frames, e.value(TRAIN), e.value(HELDOUT)) for e in evals] == [(1500, 0.1, 0.05), (3000, 0.4, 0.25)]
    assert evals[1].record is RESUMED[6]


def test_records_without_eval_frames_count_an_evaluation_where_the_values_change():
    # The single-process runner evaluates right before it records and repeats the result until the next.
    records = [{"frames": 100, TRAIN: 0.0}, {"frames": 200, TRAIN: 0.0},
               {"frames": 300, TRAIN: 0.5}, {"frames": 400, TRAIN: 0.5}]
    evals = _run(records).evaluations()
    assert [(e.frames, e.value(TRAIN)) for e in evals] == [(100, 0.0), (300, 0.5)]
    assert evals[0].value(HELDOUT) is None


def test_a_change_in_any_goal_set_or_the_averaged_weights_is_a_new_evaluation():
    records = [{"frames": 10, "eval_frames": 10, TRAIN: 0.2, HELDOUT: 0.1},
               {"frames": 20, "eval_frames": 20, TRAIN: 0.2, HELDOUT: 0.3},
               {"frames": 30, "eval_frames": 20, TRAIN: 0.2, HELDOUT: 0.3, "success_rate_eval_train_averaged": 0.9}]
    evals = _run(records).evaluations()
    # The third record's averaged score came out with the evaluation at 20 frames: the last one there wins.
    assert [(e.frames, e.value(HELDOUT)) for e in evals] == [(10, 0.1), (20, 0.3)]
    assert evals[1].value("success_rate_eval_train_averaged") == 0.9


def test_the_figures_the_bench_and_the_table_read_the_same_evaluations():
    run = _run(RESUMED)
    assert final(run, TRAIN) == pytest.approx((0.1 + 0.4) / 2)
    assert bench_evaluations(RESUMED) == [{"frames": 1500, "success": 0.1, "seconds": 10.0},
                                          {"frames": 3000, "success": 0.4, "seconds": 25.0}]
    rows = curve_rows(run)  # each evaluation's first record, then the run's last record
    assert [(r["frames"], r["greedy_train"]) for r in rows] == [("2000", "0.100"), ("3100", "0.400"),
                                                                ("3300", "0.400")]
