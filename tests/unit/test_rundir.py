"""The run directory: metrics lines, atomic checkpoints without pickle, optional TensorBoard scalars."""
import json

import numpy as np
import torch

from higher_dist.rundir import RunDir, read_metrics


def test_checkpoint_round_trip_keeps_arrays_tensors_and_numbers(tmp_path):
    rd = RunDir(tmp_path)
    state = {"a": np.arange(5, dtype=np.int16), "t": torch.ones(3), "n": 7, "nested": [{"b": np.zeros((2, 2))}],
             "rng": np.random.default_rng(3).bit_generator.state}
    rd.save_checkpoint("learner", state)
    back = rd.load_checkpoint("learner")
    assert back["a"].dtype == np.int16 and (back["a"] == np.arange(5)).all()
    assert torch.equal(back["t"], torch.ones(3)) and back["n"] == 7
    assert back["nested"][0]["b"].shape == (2, 2)
    rng = np.random.default_rng()
    rng.bit_generator.state = back["rng"]
    assert rng.random() == np.random.default_rng(3).random()
    assert not list(tmp_path.glob("*.tmp*"))  # the temporary file was renamed over


def test_a_torn_last_metrics_line_is_skipped(tmp_path):
    rd = RunDir(tmp_path)
    rd.append_metrics({"frames": 1})
    rd.append_metrics({"frames": 2})
    with open(rd.metrics_path, "a") as f:
        f.write('{"frames": 3, "upd')  # a crash mid-write
    assert [r["frames"] for r in read_metrics(rd.metrics_path)] == [1, 2]


def test_tensorboard_event_files_hold_the_metrics(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    rd = RunDir(tmp_path, tensorboard=True)
    for frames in (100, 200):
        rd.append_metrics({"frames": frames, "success_rate_train": frames / 1000, "preset": "her", "gate": True})
    acc = EventAccumulator(str(tmp_path / "tensorboard"))
    acc.Reload()
    events = acc.Scalars("success_rate_train")
    assert [(e.step, round(e.value, 3)) for e in events] == [(100, 0.1), (200, 0.2)]
    assert "preset" not in acc.Tags()["scalars"] and "gate" not in acc.Tags()["scalars"]
    assert json.loads(rd.metrics_path.read_text().splitlines()[0])["frames"] == 100


def test_last_record_reads_only_the_tail_and_skips_a_torn_line(tmp_path):
    from higher_dist.rundir import last_record

    path = tmp_path / "metrics.jsonl"
    assert last_record(path) is None
    lines = [json.dumps({"frames": i, "pad": "x" * 100}) for i in range(2000)]
    path.write_text("\n".join(lines) + "\n" + '{"frames": 99')  # a crash mid-write leaves a torn line
    assert last_record(path)["frames"] == 1999
    # A window that cuts into a line still finds the newest whole one.
    assert last_record(path, max_bytes=150)["frames"] == 1999
    assert last_record(path, max_bytes=10) is None
