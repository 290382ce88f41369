"""Nothing a peer sends can kill a role: a real learner and a real relabeler take 10,000 messages that pass
the codec's schema but are wrong for the run (every class in tests/support/mutate.py: wrong-length and
out-of-vocabulary missions, all-PAD and ungrammatical ones, missions that do not name their goal, attributes
and cells the world cannot hold, outcomes that contradict rewards, the last action or the pick, relabelled
copies from actors or contradicting their goal, unknown actor ids, over-long episodes, batches of thousands
of episodes near the schema's limits, wrong view sizes, lengths that do not add up, unexpected types), then
honest episodes. Both processes must stay alive, the learner must keep updating, every honest episode must
arrive, and the reject counters must add up, reason by reason.
"""
from __future__ import annotations

import collections
import time

import numpy as np
import pytest
import zmq

from hd_harness import Proc, RunWatch, entry, push_socket
from higher_dist.config_presets import make_config
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import codec
from higher_dist.wire.episodes import pack_episodes
from support.mutate import MUTATIONS, Pools, hostile_message
from higher_dist.world.spec import WorldSpec

pytestmark = pytest.mark.slow

MESSAGES = 10_000
HUGE = 4  # batches of thousands of episodes: each is tens of MB to build and check
SETTINGS = {"replay.min_size": 300, "replay.samples_per_insert": 1, "dqn.batch_size": 32,
            "network.conv_channels": "[16]", "stats_every_s": 0.5, "checkpoint_every_s": 600}


def _flags() -> list[str]:
    flags = ["--preset", "her", "--world", "small", "--actors", "1", "--frames", "100000000"]
    for key, value in SETTINGS.items():
        flags += ["--set", f"{key}={value}"]
    return flags


def test_ten_thousand_wrong_messages_kill_nothing_and_lose_nothing(tmp_path):
    cfg = make_config("her", "small", actors=1)
    spec = WorldSpec.of(cfg.world)
    port = free_base_port()
    endpoints = Endpoints.from_base("127.0.0.1", port)
    run_dir = tmp_path / "run"
    learner = Proc(entry("learner", *_flags(), "--run-dir", run_dir, "--port-base", port), tmp_path / "l.out", tmp_path)
    relabeler = Proc(entry("relabeler", "--learner", endpoints.control, "--state-dir", tmp_path / "rl"),
                     tmp_path / "r.out", tmp_path)
    watch = RunWatch(run_dir, [learner, relabeler])
    ctx = zmq.Context()
    try:
        watch.wait_for("the relabeler registered",
                       lambda r: any(row["role"] == "relabeler" and row["state"] == "alive" for row in r["roles"]),
                       timeout=120)
        to_learner, to_relabeler = push_socket(ctx, endpoints.experience), push_socket(ctx, endpoints.episodes)
        rng = np.random.default_rng(12)
        pools = Pools.of(real_episodes(cfg.world, 600, seed=3))
        kinds = sorted(k for k in MUTATIONS if k != "huge_batch")
        expected: collections.Counter = collections.Counter()
        sent = collections.Counter()
        for i in range(MESSAGES):
            at_relabeler = i % 2 == 1
            if i % 97 == 0 and not at_relabeler:
                # A message of a type the experience socket never carries.
                to_learner.send_multipart(codec.encode("stats", {"role": "actor", "id": 0, "values": {}}))
                expected["unexpected_type"] += 1
                sent["unexpected_type"] += 1
                continue
            kind = "huge_batch" if i < 2 * HUGE else kinds[int(rng.integers(len(kinds)))]
            sender = "actor0" if at_relabeler else ("relabeler" if rng.random() < 0.8 else "actor0")
            h = hostile_message(kind, pools, rng, spec, sender, to_relabeler=at_relabeler)
            (to_relabeler if at_relabeler else to_learner).send_multipart(h.frames)
            expected[h.reason] += h.rejects
            sent[kind] += 1
        assert sum(sent.values()) == MESSAGES

        # Then honest experience, as an actor sends it, through the relabeler: two rounds, so that the
        # learner must go on updating for the second one (it updates only while behind its replay ratio).
        def send_honest(seed: int) -> list:
            honest = real_episodes(cfg.world, 240, seed=seed)
            for start in range(0, len(honest), 8):
                to_relabeler.send_multipart(codec.encode("episodes", *pack_episodes(honest[start:start + 8]),
                                                         sender="actor0"))
            return honest

        honest = send_honest(99)
        total = sum(expected.values())

        def settled(r):
            by_reason = r.get("rejects_by_reason") or {}
            return r["episodes"] == len(honest) and sum(by_reason.values()) >= total and r["updates"] > 0

        record = watch.wait_for("every honest episode in and every reject counted", settled, timeout=400)
        honest += send_honest(98)
        later = watch.wait_for("the second round in and the learner updating on it",
                               lambda r: r["episodes"] == len(honest) and r["updates"] > record["updates"],
                               timeout=300)
        frames = sum(ep.length for ep in honest)
        wrong_picks = sum(ep.outcome == 1 for ep in honest)
        assert learner.running() and relabeler.running()
        # Nothing honest lost: every original frame, every expert copy of a wrong pick.
        assert later["frames"] == frames and later["episodes"] == len(honest)
        assert later["relabelled_episodes"] == wrong_picks
        # The counters add up, reason by reason, and nothing needed the last-resort handler.
        by_reason = {k: v for k, v in later["rejects_by_reason"].items() if v}
        assert by_reason == dict(expected), (by_reason, dict(expected))
        assert later["handler_errors"] == 0
        print(f"\nsent {MESSAGES} hostile messages ({dict(sent)}); rejects by reason: {by_reason}")
    finally:
        ctx.destroy(linger=0)
        watch.cleanup()
