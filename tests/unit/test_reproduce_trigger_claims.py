"""The trigger experiment's table per run: dataset sizes, exploring success and the gate's opening, read
from synthetic records worked out by hand."""
from __future__ import annotations

from pathlib import Path

from higher_dist.analysis.runs import Run
from higher_dist.reproduce import trigger_claims


def _run(seed, rows):
    return Run(Path(f"/nonexistent/s{seed}"), "higher", seed, "paper", rows)


def _record(frames, pairs, success, gate):
    return {"frames": frames, "relabel_dataset_size": pairs, "success_rate_train": success, "relabel_gate_open": gate}


def _cells(line):
    return [c.strip() for c in line.strip("|").split("|")]


def test_each_cell_is_the_record_nearest_its_frame_and_the_gate_its_first_opening():
    early = _run(0, [_record(f, f // 100, 0.1, f > 0) for f in range(0, 1_000_001, 10_000)])
    late = _run(1, [_record(0, None, 0.05, None)] +
                [_record(f, f // 1000, 0.02 + f / 5e6, f >= 432_100) for f in range(1000, 1_000_001, 100_000)])
    never = _run(0, [_record(f, 7, 0.04, False) for f in (0, 450_000, 990_000)])
    lines = trigger_claims.table({0: [early], 2000: [never], 1000: [late]}, 1_000_000)

    assert _cells(lines[0]) == ["trigger", "seed", "pairs at 100k frames", "200k", "400k", "600k", "800k", "1M",
                                "exploring success at 100k, 400k, 1M", "relabelling began"]
    rows = [_cells(line) for line in lines[2:]]
    assert [r[0] for r in rows] == ["0 pairs", "1000 pairs", "2000 pairs"]  # ordered by the trigger
    assert rows[0][2:8] == ["1,000", "2,000", "4,000", "6,000", "8,000", "10,000"]
    assert rows[0][9] == "at once"  # opened at 10k frames, the archive's first record after 0
    # late: records at 1k, 101k, 201k...; 100k reads 101k's 101 pairs, 1M reads 901k's 901
    assert rows[1][2:8] == ["101", "201", "401", "601", "801", "901"]
    assert rows[1][8] == "4%, 10%, 20%"  # 0.02 + f / 5e6 at 101k, 401k, 901k
    assert rows[1][9] == "501k"  # the first record at or past 432,100 frames
    assert rows[2][2] == "7" and rows[2][9] == "not by 990k"  # its own last record, not the budget


def test_the_columns_follow_the_runs_budget_and_a_run_without_the_metric_reads_a_dash():
    run = _run(2, [{"frames": f, "success_rate_train": 0.5} for f in range(0, 2_000_001, 50_000)])
    lines = trigger_claims.table({1000: [run]}, 2_000_000)
    assert _cells(lines[0])[2:8] == ["pairs at 200k frames", "400k", "800k", "1.2M", "1.6M", "2M"]
    row = _cells(lines[2])
    assert row[2:8] == ["-"] * 6 and row[8] == "50%, 50%, 50%" and row[9] == "not by 2M"
    assert trigger_claims.table({}, 1_000_000) == []


def test_a_shorter_run_reads_a_dash_past_its_own_budget_in_a_table_of_longer_runs():
    def rows(budget, end):
        return [{"frames": f, "frames_budget": budget, "relabel_dataset_size": f // 1000, "success_rate_train": 0.3,
                 "relabel_gate_open": False} for f in range(0, end + 1, 10_000)]
    short, full = _run(0, rows(1_000_000, 1_000_000)), _run(1, rows(2_000_000, 2_000_000))
    lines = trigger_claims.table({0: [short], 2000: [full]}, 2_000_000)
    short_row, full_row = _cells(lines[2]), _cells(lines[3])
    # columns 200k, 400k, 800k, 1.2M, 1.6M, 2M: the 1M run stops at 800k, the 2M run reads all six
    assert short_row[2:8] == ["200", "400", "800", "-", "-", "-"]
    assert full_row[2:8] == ["200", "400", "800", "1,200", "1,600", "2,000"]
    assert short_row[8] == "30%, 30%, -" and short_row[9] == "not by 1M"
