"""Nothing a peer sends kills a role on a BabyAI level of any kind: a real learner and a real relabeler of a
pickup, a go-to and an open level's run each take hundreds of wrong messages (every lie of
tests/support/babyai_lies.py about that level's kind, several times each, episodes of our FetchAttr world,
relabelled copies from an actor), then honest episodes through the relabeler. Both stay alive, every honest
episode arrives with its expert copies (one per outcome, up to relabel.max_per_episode), the learner updates,
and the reject counters add up for the messages whose reason is known."""
from __future__ import annotations

import collections

import numpy as np
import pytest
import zmq

from hd_harness import Proc, RunWatch, entry, push_socket
from higher_dist.config_presets import make_config
from higher_dist.launch.topology import Endpoints, free_base_port
from higher_dist.learning.episode import TIMEOUT
from higher_dist.learning.hindsight.relabel import ExpertRelabel, make_relabel_strategy, relabel_candidates
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import codec
from higher_dist.wire.episodes import pack_episodes
from higher_dist.world.spec import WorldSpec
from support.babyai_lies import COPY_LIES, ORIGINAL_LIES, lie, lies_for

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

# Level -> (wrong messages, real episodes the lies are made from, honest episodes sent after them). The open
# level's random episodes run to 576 steps: fewer of them, and fewer messages, keep each case within about
# two minutes on a shared machine.
LEVELS = {"BabyAI-PickupDist-v0": (2_000, 300, 240), "BabyAI-GoToLocal-v0": (1_500, 150, 120),
          "BabyAI-OpenDoorLoc-v0": (800, 40, 30)}
SETTINGS = {"replay.min_size": 300, "replay.samples_per_insert": 1, "dqn.batch_size": 32, "dqn.compile": "false",
            "network.conv_channels": "[16]", "stats_every_s": 0.5, "checkpoint_every_s": 600}


@pytest.mark.parametrize("level", LEVELS)
def test_wrong_messages_on_a_level_kill_nothing_and_lose_nothing(tmp_path, level):
    messages, pool_size, honest_size = LEVELS[level]
    cfg = make_config("her", level)
    spec = WorldSpec.of(cfg.world)
    lies = lies_for(spec.level_kind)
    port = free_base_port()
    endpoints = Endpoints.from_base("127.0.0.1", port)
    flags = ["--preset", "her", "--world", level, "--actors", "1", "--frames", "100000000"]
    for key, value in SETTINGS.items():
        flags += ["--set", f"{key}={value}"]
    run_dir = tmp_path / "run"
    learner = Proc(entry("learner", *flags, "--run-dir", run_dir, "--port-base", port), tmp_path / "l.out", tmp_path)
    relabeler = Proc(entry("relabeler", "--learner", endpoints.control, "--state-dir", tmp_path / "rl"),
                     tmp_path / "r.out", tmp_path)
    watch = RunWatch(run_dir, [learner, relabeler])
    ctx = zmq.Context()
    try:
        # The episodes are made while the roles start.
        pool = real_episodes(cfg.world, pool_size, seed=3)
        honest = real_episodes(cfg.world, honest_size, seed=99)
        fetchattr = real_episodes(make_config("her", "paper").world, 60, seed=3)
        watch.wait_for("the relabeler registered",
                       lambda r: any(row["role"] == "relabeler" and row["state"] == "alive" for row in r["roles"]),
                       timeout=180)
        to_learner, to_relabeler = push_socket(ctx, endpoints.experience), push_socket(ctx, endpoints.episodes)
        rng = np.random.default_rng(12)
        expected: collections.Counter = collections.Counter()
        sent: collections.Counter = collections.Counter()
        unknown_reason = 0  # random damage: dropped under some reason, or harmless
        for i in range(messages):
            kind = lies[int(rng.integers(len(lies)))]
            if i % 10 == 0:  # our own world's episodes: not this level's (a whole batch of them)
                batch = [fetchattr[int(j)] for j in rng.integers(len(fetchattr), size=4)]
                to_learner.send_multipart(codec.encode("episodes", *pack_episodes(batch), sender="relabeler"))
                unknown_reason += len(batch)
                continue
            if i % 10 == 1:  # a relabelled copy from an actor, at the relabeler
                start = int(rng.integers(len(pool) // 3))
                failed = next(ep for ep in pool[start:] if ep.outcome == TIMEOUT and ep.pick_step >= 0)
                copy = ExpertRelabel(spec=spec).relabel([failed])
                to_relabeler.send_multipart(codec.encode("episodes", *pack_episodes(copy), sender="actor0"))
                expected["relabel_origin"] += len(copy)
                continue
            bad, reason = lie(kind, pool, spec, rng)
            if kind in ORIGINAL_LIES and i % 2:
                to_relabeler.send_multipart(codec.encode("episodes", *pack_episodes([bad]), sender="actor0"))
            else:
                to_learner.send_multipart(codec.encode("episodes", *pack_episodes([bad]), sender="relabeler"))
            expected[reason] += 1
            sent[kind] += 1
        assert set(sent) == set(lies) and min(sent.values()) >= 5, sent  # every lie, several times
        assert set(COPY_LIES) <= set(lies)

        for start in range(0, len(honest), 8):
            to_relabeler.send_multipart(codec.encode("episodes", *pack_episodes(honest[start:start + 8]),
                                                     sender="actor0"))
        # The copies the relabeler makes: one per outcome of each failure that achieved one, up to
        # relabel.max_per_episode (the real strategy, run here on the same episodes, makes as many).
        candidates = relabel_candidates(honest)
        copies = sum(min(ep.n_outcomes, cfg.relabel.max_per_episode) for ep in candidates)
        assert copies == len(make_relabel_strategy(cfg, 0).relabel(honest)) > len(candidates)
        total = sum(expected.values()) + unknown_reason

        def settled(r):
            by_reason = r.get("rejects_by_reason") or {}
            return (r["episodes"] == len(honest) and r["relabelled_episodes"] >= copies
                    and sum(by_reason.values()) >= total and r["updates"] > 0)

        later = watch.wait_for("every honest episode and its copies in and every reject counted", settled,
                               timeout=500)
        assert learner.running() and relabeler.running()
        assert later["frames"] == sum(ep.length for ep in honest) and later["episodes"] == len(honest)
        assert later["relabelled_episodes"] == copies  # every honest failure's expert copies, no more
        by_reason = {k: v for k, v in later["rejects_by_reason"].items() if v}
        for reason, count in expected.items():
            assert by_reason.get(reason, 0) >= count, (reason, by_reason, dict(expected))
        assert sum(by_reason.values()) == total, (by_reason, dict(expected), unknown_reason)
        assert later["handler_errors"] == 0
    finally:
        ctx.destroy(linger=0)
        watch.cleanup()
