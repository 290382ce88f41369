"""End to end: `higher-reproduce` runs a tiny plan (two methods, one seed, the small world) as real cluster
process trees, is stopped by SIGTERM to its process group in the middle, resumes from the checkpoints
when run again, skips what is finished on a third run, and leaves figures and a results table that hold
numbers; its archive reports the same tables and resumes as done. `make reproduce -- --dry-run` prints a plan and its cost without running anything."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hd_harness import Proc, RunWatch, tail

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
BUDGET = 1200
FAST = ["--set", "replay.min_size=200", "--set", "dqn.batch_size=32", "--set", "stats_every_s=0.5",
        "--set", "eval.episodes=8"]


def reproduce(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from higher_dist.cli import reproduce_main as m; sys.exit(m())",
            "main", "--world", "small", "--frames", str(BUDGET), "--seeds", "1", "--methods", "dqn,her",
            "--parallel", "2", "--out", str(out), *FAST, *extra]


def frames_of(run_dir: Path) -> list[int]:
    from higher_dist.rundir import read_metrics

    return [int(r["frames"]) for r in read_metrics(run_dir / "metrics.jsonl")]


def test_a_tiny_plan_stops_resumes_and_reports(tmp_path):
    out = tmp_path / "plan"
    runs = {name: out / "runs" / name for name in ("dqn-s0", "her-s0")}
    first = Proc(reproduce(out), tmp_path / "first.log", cwd=tmp_path)
    watch = RunWatch(runs["her-s0"], [first])
    try:
        # Stop in the middle: once a run is a quarter of the way (both run at once).
        def midway():
            return max((frames_of(p) or [0])[-1] for p in runs.values()) >= BUDGET // 4
        watch.wait_until("a run a quarter of the way", midway, timeout=120)
        assert json.loads((out / "plan.json").read_text())["runs"].keys() == {"dqn-s0", "her-s0"}
        first.snapshot()
        os.killpg(first.pid, signal.SIGTERM)  # the whole group: reproduce, its clusters and their roles
        rc = first.wait(90)
        assert rc == 128 + signal.SIGTERM, tail(first.output())
        assert "rerun the same command to resume" in first.output()
        assert not watch.leftovers(), watch.leftovers()
        stopped = [name for name, p in runs.items() if (p / "learner.ckpt").exists() and frames_of(p)[-1] < BUDGET]
        assert stopped, "the SIGTERM came after both runs finished: nothing to resume\n" + first.output()

        second = watch.add(Proc(reproduce(out), tmp_path / "second.log", cwd=tmp_path))
        rc = second.wait(150)
        assert rc == 0, tail(second.output(), 60) + watch.diagnostics()
        for name in stopped:
            assert re.search(rf"{name}: resumed at \d+ frames", second.output()), second.output()
        for name, path in runs.items():
            frames = frames_of(path)
            assert frames[-1] >= BUDGET, (name, frames[-3:])
            assert frames == sorted(frames), f"{name}: the curve steps back after the resume: {frames}"
        assert not watch.leftovers(), watch.leftovers()

        third = watch.add(Proc(reproduce(out, "--no-report"), tmp_path / "third.log", cwd=tmp_path))
        assert third.wait(60) == 0, tail(third.output())
        assert "started" not in third.output() and "resumed" not in third.output(), third.output()
    finally:
        watch.cleanup()

    figures = out / "figures"
    for name in ("success_train", "success_heldout", "replay_composition"):
        png = (figures / f"{name}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and 5_000 < len(png) < 200_000, name
    results = (out / "results.md").read_text()
    rows = {line.split("|")[1].strip(): line for line in results.splitlines() if line.startswith("| DQN")}
    for label in ("DQN", "DQN+HER"):
        assert re.search(r"\d+\.\d% \+- \d+\.\d \(1 seed, [\d,]+ frames\)", rows[label]), rows[label]
    claim = next(line for line in results.splitlines() if line.startswith("| DQN stays near random"))
    assert re.search(r"\*\*(holds|does not hold|mixed)\*\*", claim) and re.search(r"\d+\.\d%", claim), claim
    assert "not measured" in next(line for line in results.splitlines() if "trigger point" in line)
    assert "figures/success_train.png" in results

    # The archive (what git keeps of a plan) reports the same tables, and a copy of it resumes as done.
    archived = tmp_path / "archive"
    run = subprocess.run(reproduce(out, "--archive", str(archived)), capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "2 finished runs archived" in run.stdout, run.stdout + run.stderr
    assert not list(archived.glob("runs/*/*.ckpt"))
    run = subprocess.run(reproduce(archived, "--report"), capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    tables = lambda text: [line for line in text.splitlines() if line.startswith("| DQN")]  # noqa: E731
    assert tables((archived / "results.md").read_text()) == tables(results)
    fourth = Proc(reproduce(archived, "--no-report"), tmp_path / "fourth.log", cwd=tmp_path)
    assert fourth.wait(60) == 0, tail(fourth.output())
    assert "started" not in fourth.output() and "resumed" not in fourth.output(), fourth.output()


def test_make_reproduce_dry_run_prints_the_plan_and_its_cost(tmp_path):
    out = tmp_path / "never"
    proc = subprocess.run(["make", "-s", "reproduce", "--", "--dry-run", "--seeds", "2", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    text = proc.stdout
    for name in ("dqn-s1", "higher-s0", "noisy-her-p0.5-s1", "higher-trigger2000-s0", "gen-pairs5000-s1"):
        assert re.search(rf"^{re.escape(name)}\s", text, re.M), name
    # 4 main + 3 noisy + 3 trigger cluster runs and 5 generator runs per seed; DQN and HER are shared.
    assert "30 runs (20 cluster runs, 10 generator runs); 100,000,000 env frames left" in text
    assert re.search(r"estimated cost on this machine .*: [\d.]+ (days|h|min) wall-clock", text)
    assert "frame rate used:" in text
    assert not out.exists()
