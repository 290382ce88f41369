"""End to end: a learner stopped with SIGTERM and resumed from its checkpoint publishes the checkpoint's
weights, keeps its counters and clock, and learning goes on with a resumed relabeler and a new actor.
Real processes, real sockets, 127.0.0.1 only."""
from __future__ import annotations

import copy
import signal

import numpy as np
import pytest
import zmq

from hd_harness import Proc, RunWatch, config_flags, entry, read_text
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.rundir import RunDir
from higher_dist.wire import codec

pytestmark = pytest.mark.slow


def _online_weights(state) -> dict[str, np.ndarray]:
    return {k: v.numpy() for k, v in state["core"]["dqn"]["online"].items()}


def test_learner_resumes_from_its_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    port_base = free_base_port()
    control = f"tcp://127.0.0.1:{port_base}"
    flags = config_flags(10_000_000, actors=1, checkpoint_every_s=None)
    watch = RunWatch(run_dir)

    def learner(*extra):
        return watch.add(Proc(entry("learner", *flags, "--run-dir", run_dir, "--port-base", port_base, *extra),
                              tmp_path / "learner.out", tmp_path))

    def helpers(resume: bool):
        relabeler = watch.add(Proc(entry("relabeler", "--learner", control, "--state-dir", run_dir,
                                         *(["--resume"] if resume else [])), tmp_path / "relabeler.out", tmp_path))
        actor = watch.add(Proc(entry("actor", "--learner", control, "--actor-id", "0"),
                               tmp_path / "actor.out", tmp_path))
        return relabeler, actor

    ctx = zmq.Context()
    try:
        # 1. A learner, a relabeler and an actor, started by hand; stopped with SIGTERM after some updates.
        first = learner()
        relabeler, actor = helpers(resume=False)
        watch.wait_for("updates >= 40", lambda r: r["updates"] >= 40, timeout=150)
        first.send(signal.SIGTERM)
        assert first.wait(30) == 0, watch.diagnostics()
        # The learner's stop reaches the others: they end too, cleanly.
        assert relabeler.wait(30) == 0 and actor.wait(30) == 0, watch.diagnostics()
        rd = RunDir(run_dir)
        saved = rd.load_checkpoint("learner")
        assert saved is not None
        counters = copy.deepcopy(saved["core"]["counters"])
        assert counters["updates"] >= 40 and counters["frames"] > 0
        stop_record = rd.read_metrics()[-1]
        assert stop_record["updates"] == counters["updates"] and stop_record["frames"] == counters["frames"]
        n_records = len(rd.read_metrics())
        assert rd.load_checkpoint("relabeler") is not None

        # 2. The learner again, with --resume, and nothing else yet: what it publishes is the checkpoint.
        weights = ctx.socket(zmq.SUB)
        weights.setsockopt(zmq.SUBSCRIBE, b"")
        weights.setsockopt(zmq.LINGER, 0)
        weights.connect(Endpoints.from_base("127.0.0.1", port_base).weights)
        second = learner("--resume")
        if not weights.poll(120_000):
            pytest.fail("no weights from the resumed learner\n" + watch.diagnostics())
        version, arrays = codec.decode_weights(weights.recv())
        # The checkpoint's online network is the one after its last update. With the replay restored, the
        # learner may go on updating at once (the samples-per-insert ratio it had left), so the first
        # weights it publishes are that version or a later one; when they are that version, exactly.
        assert version >= counters["updates"] >= saved["weights_version"]
        expected = _online_weights(saved)
        assert set(arrays) == set(expected)
        if version == counters["updates"]:
            for name, value in expected.items():
                np.testing.assert_array_equal(arrays[name], value, err_msg=name)
        first_after = watch.wait_for("a metrics record from the resumed learner", lambda r: True, timeout=60,
                                     after=n_records)
        assert first_after["updates"] >= counters["updates"]
        assert first_after["frames"] == counters["frames"]
        assert first_after["episodes"] == counters["episodes"]
        assert first_after["relabelled_episodes"] == counters["relabelled_episodes"]
        # The replay is in the checkpoint by default: the resumed learner starts with the same transitions,
        # of the same origins, before any new experience arrives (no actor is back yet).
        assert stop_record["replay_size"] > 0
        for key in ("replay_size", "replay_success", "replay_wrong_pick", "replay_timeout", "replay_relabelled"):
            assert first_after.get(key) == stop_record.get(key), key
        # The run's clock goes on from the checkpoint's running time, not from zero.
        assert saved["elapsed_s"] == pytest.approx(stop_record["elapsed_s"], abs=1.0) and saved["elapsed_s"] > 0
        assert first_after["elapsed_s"] >= round(saved["elapsed_s"], 1)
        assert f"resumed at {counters['frames']} frames, {counters['updates']} updates" in read_text(
            tmp_path / "learner.out")

        # 3. With a relabeler (resumed too) and an actor back, learning continues from there.
        relabeler, actor = helpers(resume=True)
        watch.wait_for("updates beyond the checkpoint's",
                       lambda r: r["updates"] > counters["updates"] + 10 and r["frames"] > counters["frames"],
                       timeout=150, after=n_records)
        assert "resumed the relabeler's generator and dataset" in read_text(tmp_path / "relabeler.out")
        second.send(signal.SIGTERM)
        assert second.wait(30) == 0, watch.diagnostics()
        assert relabeler.wait(30) == 0 and actor.wait(30) == 0, watch.diagnostics()
        final = rd.load_checkpoint("learner")["core"]["counters"]
        assert final["updates"] > counters["updates"] and final["frames"] > counters["frames"]
        assert watch.leftovers() == []
    finally:
        ctx.destroy(linger=0)
        watch.cleanup()
