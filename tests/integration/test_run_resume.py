"""`higher-run --resume`: the single-process runner keeps no checkpoint, so a resume is refused in one line
that says why, after a real run on the small world; a run directory that holds no run is named as such."""
from __future__ import annotations

import json
import subprocess

from hd_harness import config_flags, entry


def test_higher_run_resume_is_refused_in_one_line_naming_why(tmp_path):
    run_dir = tmp_path / "run"
    done = subprocess.run(entry("run", *config_flags(2000, 1), "--metrics-every", "1000", "--run-dir", run_dir),
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["frames"] >= 2000
    again = subprocess.run(entry("run", "--resume", "--run-dir", run_dir), capture_output=True, text=True,
                           timeout=120, cwd=tmp_path)
    assert again.returncode == 2
    lines = again.stderr.strip().splitlines()
    assert len(lines) == 1 and "higher-run: error: --resume: higher-run keeps no checkpoint" in lines[0], again.stderr
    assert "higher-cluster" in lines[0]
    assert (run_dir / "metrics.jsonl").read_text().count("\n") == len(records)  # the run is left as it was
    empty = subprocess.run(entry("run", "--resume", "--run-dir", tmp_path / "none"), capture_output=True,
                           text=True, timeout=120, cwd=tmp_path)
    assert empty.returncode == 2 and "is" in empty.stderr and "a run directory?" in empty.stderr, empty.stderr
