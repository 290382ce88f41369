"""`higher-run --resume`: a single-process run on the small world goes on from its checkpoint as the same
experiment: the counters, the replay and the clocks continue, flags that would change the run are refused
by name, and a folder without a checkpoint is refused in one line."""
from __future__ import annotations

import json
import subprocess

import pytest

from hd_harness import config_flags, entry

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]  # two short runs: about 2 minutes on an idle machine


def _records(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_higher_run_resumes_from_its_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    first = subprocess.run(entry("run", *config_flags(1000, 1, checkpoint_every_s=600), "--metrics-every", "500", "--run-dir", run_dir),
                           capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    before = _records(run_dir)
    assert before[-1]["frames"] >= 1000 and (run_dir / "runner.ckpt").exists()

    # A flag that would make it another experiment is refused by name; the run is left as it was.
    changed = subprocess.run(entry("run", "--resume", "--run-dir", run_dir, "--set", "dqn.lr=0.1"),
                             capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert changed.returncode == 2 and "dqn.lr" in changed.stderr, changed.stderr
    assert len(_records(run_dir)) == len(before)

    again = subprocess.run(entry("run", "--resume", "--run-dir", run_dir, "--frames", "2000", "--metrics-every", "500"),
                           capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"resumed {run_dir} at {before[-1]['frames']:,} frames" in again.stdout
    after = _records(run_dir)[len(before):]
    assert after and after[-1]["frames"] >= 2000
    first_after = after[0]
    # The same run going on: frames, updates, episodes and replay continue from where they stood.
    assert first_after["frames"] > before[-1]["frames"]
    assert first_after["updates"] >= before[-1]["updates"] and first_after["episodes"] >= before[-1]["episodes"]
    assert first_after["replay_size"] >= before[-1]["replay_size"]
    assert first_after["elapsed_s"] >= before[-1]["elapsed_s"]
    history = (run_dir / "history.jsonl").read_text()
    assert "frames" in history  # the extended budget is recorded in the run's history

    empty = subprocess.run(entry("run", "--resume", "--run-dir", tmp_path / "none"), capture_output=True,
                           text=True, timeout=120, cwd=tmp_path)
    assert empty.returncode == 2 and len(empty.stderr.strip().splitlines()) == 1, empty.stderr
