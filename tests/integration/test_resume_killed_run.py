"""End to end: a run killed outright (SIGKILL to the launcher and every role) right after a checkpoint, then
`higher-cluster --resume`, is the same run: the resumed learner starts from the checkpoint's counters,
replay and exploration clock, the relabeler from its generator and dataset, and the greedy curve goes on
where it was instead of dipping. Real processes, real sockets, real checkpoints, 127.0.0.1 only."""
from __future__ import annotations

import os
import signal

import numpy as np
import psutil
import pytest

from hd_harness import FAST_SETTINGS, Proc, RunWatch, entry, read_text, start_cluster
from higher_dist.config_presets import make_config
from higher_dist.launch.topology import free_base_port
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.episode import SUCCESS
from higher_dist.rundir import RunDir

pytestmark = pytest.mark.slow

# Exploration that decays from 1.0 over 200k frames: a resume that restarted the clock would explore at
# ~1.0 again, visibly above the epsilon it had when killed. A discount of 0.99 learns the small world a
# little later and its greedy curve swings less between the evaluations compared (at 0.95 it passed the
# "learned" bar at 3k frames, where 32-episode evaluations still swing by 0.3).
# The greedy curve of an uninterrupted run of these settings swings between 0.41 and 0.73 from one evaluation
# to the next (64 episodes each) while its level stays near 0.55: the policy itself moves that much between
# evaluations, not only the sampling. So the curve is judged on means of three 128-episode evaluations.
SETTINGS = {"exploration.warmup_frames": 200_000, "eval.every_frames": 1500, "eval.episodes": 128,
            "dqn.gamma": 0.99}
JUDGED = 3  # evaluations averaged on each side of the kill


def _chance() -> float:
    """Greedy success is judged against random play in the same world."""
    flat = {k: v for k, v in FAST_SETTINGS.items() if k.startswith("world.")}
    cfg = make_config("her", "small", actors=1, frames=1000, **flat)
    collector = EpisodeCollector(cfg.world, 32, cfg.network.frame_stack, seed=5)
    rng = np.random.default_rng(5)
    outcomes: list[bool] = []
    while len(outcomes) < 400:
        outcomes += [ep.outcome == SUCCESS for ep in collector.step(rng.integers(0, 4, size=collector.n_envs))]
    return float(np.mean(outcomes))


def _evaluations(records) -> list[tuple[int, float]]:
    """(frames evaluated at, greedy success on training goals), once per evaluation."""
    out: dict[int, float] = {}
    for r in records:
        if r.get("eval_frames") is not None and r.get("success_rate_eval_train") is not None:
            out.setdefault(r["eval_frames"], r["success_rate_eval_train"])
    return sorted(out.items())


def _kill_everything(launcher: Proc) -> None:
    """SIGKILL to the launcher and all its descendants at once: nothing gets to write a final checkpoint."""
    root = psutil.Process(launcher.pid)
    procs = [root, *root.children(recursive=True)]
    for p in procs:
        try:
            os.kill(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    psutil.wait_procs(procs, timeout=30)


@pytest.mark.timeout(900)
def test_a_killed_run_resumes_as_its_checkpoint_and_its_curve_does_not_dip(tmp_path):
    chance = _chance()
    run_dir = tmp_path / "run"
    watch, launcher, _ = start_cluster(run_dir, tmp_path, frames=10_000_000, actors=1, **SETTINGS)
    rd = RunDir(run_dir)
    try:
        # 1. Learned: the mean of the last three greedy evaluations clearly above chance.
        watch.wait_for("three evaluations averaging >= chance + 0.25",
                       lambda r: len(ev := _evaluations(watch.records())) >= JUDGED
                       and np.mean([s for _, s in ev[-JUDGED:]]) >= chance + 0.25, timeout=480)
        # A fresh checkpoint of both stateful roles, then SIGKILL to every process.
        marks = {role: rd.checkpoint_path(role).stat().st_mtime_ns for role in ("learner", "relabeler")}
        watch.wait_until("both roles checkpointed again",
                         lambda: all(rd.checkpoint_path(role).stat().st_mtime_ns > t for role, t in marks.items()),
                         timeout=60)
        _kill_everything(launcher)
        before = watch.records()
        evals_before = _evaluations(before)
        eps_before = before[-1]["epsilon_mean"]
        assert eps_before is not None and eps_before < 0.99

        # What resume must start from: the checkpoints as the kill left them on disk.
        saved = rd.load_checkpoint("learner")
        counters, replay = saved["core"]["counters"], saved["core"]["replay"]
        assert replay["size"] > 0, "the replay is in the checkpoint by default"
        pairs = len(rd.load_checkpoint("relabeler")["trainer"]["dataset"]["views"])
        assert pairs > 0

        # 2. Resumed from the run folder alone (its config.json), on a fresh port range.
        n = len(before)
        resumed = watch.add(Proc(entry("cluster", "--resume", "--run-dir", run_dir, "--no-dashboard",
                                       "--port-base", free_base_port()), tmp_path / "resumed.out", tmp_path))
        first = watch.wait_for("the resumed learner's first record", lambda r: True, timeout=180, after=n)
        assert first["frames"] == counters["frames"] and first["updates"] >= counters["updates"]
        assert first["episodes"] == counters["episodes"]
        assert first["replay_size"] == replay["size"]  # the same transitions, before any new experience
        assert f"resumed at {counters['frames']} frames" in watch.log("learner")
        watch.wait_until("the relabeler resumed from its checkpoint", lambda: "resumed the relabeler's generator "
                         "and dataset" in read_text(run_dir / "logs" / "relabeler.log"), timeout=120)
        acting = watch.wait_for("the actor acting again", lambda r: r.get("epsilon_mean") is not None
                                and r["frames"] > counters["frames"], timeout=180, after=n)
        # The exploration clock goes on from the checkpoint's frames: the epsilon it had, not 1.0 again.
        assert acting["epsilon_mean"] <= eps_before + 0.01, (acting["epsilon_mean"], eps_before)
        assert acting["relabel_dataset_size"] >= pairs

        # 3. No dip: the first three evaluations after the resume stay near the three before the kill.
        # Only the resumed run's records: the killed run may have evaluated past the checkpoint's frames too.
        watch.wait_for("three evaluations after the resume",
                       lambda r: len(_evaluations(watch.records()[n:])) >= JUDGED, timeout=300, after=n)
        resumed_evals = _evaluations(watch.records()[n:])
        assert all(f > counters["frames"] for f, _ in resumed_evals), (resumed_evals, counters["frames"])
        after = [s for _, s in resumed_evals[:JUDGED]]
        # Not even for a moment at the epsilon of frame 0: every record of the resumed run says so.
        resumed_eps = [r["epsilon_mean"] for r in watch.records()[n:] if r.get("epsilon_mean") is not None]
        assert resumed_eps and max(resumed_eps) <= eps_before + 0.01, (max(resumed_eps), eps_before)
        # Means of three evaluations: the uninterrupted curve's mean of three moves by about 0.05; a network or
        # replay lost in the resume would start again from chance.
        level = float(np.mean([s for _, s in evals_before[-JUDGED:]]))
        assert np.mean(after) >= level - 0.2 and np.mean(after) >= chance + 0.15, (evals_before[-JUDGED:], after,
                                                                                   chance)
        resumed.send(signal.SIGINT)
        assert resumed.wait(60) == 0, watch.diagnostics()
    finally:
        watch.cleanup()
