"""An internal error is not a bad message. A real learner (or relabeler) whose own code raises once it has
written a good checkpoint (the fault is patched in by tests/support/faulty_role.py, the process, sockets and
checkpoints are real) stops at once: exit status 70, one line on stderr naming the step and the error, no
`handler_error` counted, and the checkpoint on disk is byte for byte the last good one, which a restart
with --resume goes on from. The supervisor of higher-cluster restarts such a role with --resume and quotes
its cause. (That a malformed message is still only dropped and counted is test_semantic_fuzz.py's and
tests/unit/test_wire_fuzz.py's.)"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path

import pytest

from hd_harness import Proc, RunWatch, config_flags, entry, read_text
from higher_dist import metrics as m
from higher_dist.launch.local_cluster import RoleProcess, Supervisor
from higher_dist.launch.parent import INTERNAL_ERROR_EXIT
from higher_dist.launch.topology import free_base_port
from higher_dist.roles.evaluator import BackgroundEvaluator
from higher_dist.roles.loop import InternalError, internal, stop_on_internal_error
from higher_dist.rundir import RunDir

pytestmark = pytest.mark.slow

FAULTY = Path(__file__).resolve().parents[1] / "support" / "faulty_role.py"


def faulty(target: str, checkpoints: int, skip: int, record: Path, role: str, *flags) -> list[str]:
    return [sys.executable, str(FAULTY), target, str(checkpoints), str(skip), str(record), role, *map(str, flags)]


def written(record: Path) -> list[dict]:
    return [json.loads(line) for line in read_text(record).splitlines() if line.strip()]


def on_disk(path: str) -> dict:
    return {"path": path, "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
            "mtime_ns": os.stat(path).st_mtime_ns}


def cause_lines(text: str, role: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(f"{role}: internal error in ")]


def test_a_learner_that_fails_in_its_replay_insert_stops_keeps_its_checkpoint_and_resumes(tmp_path):
    run_dir, record = tmp_path / "run", tmp_path / "checkpoints.jsonl"
    port_base = free_base_port()
    control = f"tcp://127.0.0.1:{port_base}"
    flags = [*config_flags(10_000_000, actors=1), "--run-dir", run_dir, "--port-base", port_base]
    watch = RunWatch(run_dir)
    try:
        # The second episode written after the third checkpoint (every 2 s: experience has come in by then)
        # raises: part-way through a batch insert.
        learner = watch.add(Proc(faulty("higher_dist.learning.replay:PrioritizedReplay._write", 3, 1, record,
                                        "learner", *flags), tmp_path / "learner.out", tmp_path))
        relabeler = watch.add(Proc(entry("relabeler", "--learner", control, "--state-dir", tmp_path / "rl"),
                                   tmp_path / "relabeler.out", tmp_path))
        actor = watch.add(Proc(entry("actor", "--learner", control, "--actor-id", "0"), tmp_path / "actor.out",
                               tmp_path))
        code = learner.wait(180)
        assert code == INTERNAL_ERROR_EXIT, watch.diagnostics()
        out = learner.output()
        good = written(record)
        assert len(good) >= 3, out  # more than 3 when no insert came between two checkpoints
        lines = cause_lines(out, "learner")
        assert lines == [f"learner: internal error in replay insert: RuntimeError: injected fault in "
                         f"PrioritizedReplay._write (last good checkpoint kept: {good[-1]['path']})"], out
        # The checkpoint is the good one, untouched: nothing of the state that raised was written.
        assert on_disk(good[-1]["path"]) == good[-1]
        assert "handler_error" not in out and "learner stopped:" not in out
        records = RunDir(run_dir).read_metrics()
        assert records and all(r[m.HANDLER_ERRORS] == 0 for r in records)
        # Told nothing (as after a crash), the relabeler and the actor are still running.
        assert relabeler.running() and actor.running(), watch.diagnostics()

        saved = RunDir(run_dir).load_checkpoint("learner")["core"]["counters"]
        assert saved["frames"] > 0, "the fault came before any experience: nothing to keep"
        watch.procs.remove(learner)  # its exit is the point; the resumed learner is watched from here
        n = len(records)
        resumed = watch.add(Proc(entry("learner", *flags, "--resume"), tmp_path / "resumed.out", tmp_path))
        watch.wait_for("updates and frames beyond the checkpoint's",
                       lambda r: r[m.UPDATES] > saved["updates"] + 10 and r[m.FRAMES] > saved["frames"],
                       timeout=150, after=n)
        assert f"resumed at {saved['frames']} frames, {saved['updates']} updates" in resumed.output()
        resumed.send(signal.SIGTERM)
        assert resumed.wait(30) == 0, watch.diagnostics()
        assert relabeler.wait(30) == 0 and actor.wait(30) == 0, watch.diagnostics()
    finally:
        watch.cleanup()


def test_a_relabeler_that_fails_in_its_relabelling_stops_and_keeps_its_checkpoint(tmp_path):
    run_dir, state_dir, record = tmp_path / "run", tmp_path / "rl", tmp_path / "checkpoints.jsonl"
    port_base = free_base_port()
    control = f"tcp://127.0.0.1:{port_base}"
    watch = RunWatch(run_dir)
    try:
        learner = watch.add(Proc(entry("learner", *config_flags(10_000_000, actors=1), "--run-dir", run_dir,
                                       "--port-base", port_base), tmp_path / "learner.out", tmp_path))
        relabeler = watch.add(Proc(faulty("higher_dist.roles.relabeler:RelabelerService.relabel", 1, 0, record, "relabeler",
                                          "--learner", control, "--state-dir", state_dir),
                                   tmp_path / "relabeler.out", tmp_path))
        watch.add(Proc(entry("actor", "--learner", control, "--actor-id", "0"), tmp_path / "actor.out", tmp_path))
        assert relabeler.wait(180) == INTERNAL_ERROR_EXIT, watch.diagnostics()
        out = relabeler.output()
        good = written(record)
        assert good, out
        assert cause_lines(out, "relabeler") == [
            f"relabeler: internal error in relabelling: RuntimeError: injected fault in RelabelerService.relabel "
            f"(last good checkpoint kept: {good[-1]['path']})"], out
        assert on_disk(good[-1]["path"]) == good[-1]
        assert "handler_error" not in out
        assert learner.running(), watch.diagnostics()
    finally:
        watch.cleanup()


def test_the_supervisor_restarts_a_role_that_stopped_on_an_internal_error_with_resume_and_says_why(tmp_path):
    rd = RunDir(tmp_path / "run")
    (rd.path / "logs").mkdir(parents=True)
    rd.checkpoint_path("learner").write_bytes(b"the last good checkpoint")
    line = "learner: internal error in DQN update: ValueError: bad (last good checkpoint kept: x)"
    stops = [sys.executable, "-c", f"import sys; print('noise'); print({line!r}, file=sys.stderr); sys.exit(70)"]
    role = RoleProcess("learner", list(stops), rd.path / "logs" / "learner.log")
    sup = Supervisor([role], max_restarts=1, run_dir=rd, quiet=True)
    sup.start_all()
    deadline = time.time() + 30
    while role.restarts < 2 and time.time() < deadline:
        assert sup.poll() or role.restarts == 2
        time.sleep(0.1)
    said = read_text(rd.path / "logs" / "cluster.log")
    assert f"learner exited with code 70, {line}; restart in 1 s" in said, said
    assert "restarting learner (restart 1)" in said and role.argv == [*stops, "--resume"]
    assert f"giving up: learner crashed 2 times (last exit code 70, {line})" in said, said
    assert sup.exit_code == 1


def test_an_evaluation_that_raises_stops_the_learner_with_a_named_one_line_cause(capsys):
    """The evaluation runs on a thread of the learner: its exception is raised again in the learner's loop,
    named as the evaluation's, and said in one line (a fake agent: no environments needed)."""

    class BrokenAgent:
        def policy(self):
            return None

        def evaluate_weights(self, policy, weights, averaged, frames):
            raise ValueError(f"non-finite Q-values at {frames} frames")

    evaluator = BackgroundEvaluator(BrokenAgent())
    evaluator.check()  # nothing has failed yet
    assert evaluator.start({}, 1200)
    evaluator.wait()
    with pytest.raises(InternalError) as caught:
        with internal("evaluation"):
            evaluator.check()
    assert str(caught.value) == "internal error in evaluation: ValueError: non-finite Q-values at 1200 frames"
    code = stop_on_internal_error("learner", caught.value, "last good checkpoint kept: run/learner.ckpt",
                                  logging.getLogger("test"))
    assert code == INTERNAL_ERROR_EXIT == 70
    assert capsys.readouterr().err.splitlines() == [
        "learner: internal error in evaluation: ValueError: non-finite Q-values at 1200 frames "
        "(last good checkpoint kept: run/learner.ckpt)"]
