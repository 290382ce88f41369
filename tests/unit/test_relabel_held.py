"""relabel.held_while_gated: the failed episodes a learned relabeller holds while its gate is shut, and
relabels once it opens."""
from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest
import torch
from test_relabel import GEN, check_copies, mixed_batch, trained, wrong_picks  # noqa: F401 (a fixture)

from higher_dist.config_presets import make_config
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.episode import Episode
from higher_dist.learning.hindsight.relabel import (HELD_RELEASE, LearnedRelabel, make_relabel_strategy,
                                                    relabel_candidates)
from higher_dist.rundir import RunDir
from higher_dist.wire.codec import decode, encode
from higher_dist.wire.episodes import pack_episodes, unpack_episodes
from higher_dist.world.spec import WorldSpec
from higher_dist.world.language import parse

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def opened_generator(trained) -> dict:
    """The trainer state of a generator whose gate has opened (test_relabel's `trained`)."""
    return trained.trainer.state_dict()


def fields_of(ep: Episode) -> dict:
    return {f.name: getattr(ep, f.name) for f in fields(ep)}


def frames_key(ep: Episode) -> bytes:
    return ep.frames.tobytes()


def test_the_newest_failures_are_held_while_shut_and_relabelled_in_slices_once_open(opened_generator):
    held = 300
    strategy = LearnedRelabel(GEN, seed=0, held_while_gated=held)
    offered = wrong_picks(400, "train", seed=11)
    batch, wrong = mixed_batch(seed=12)  # successes, a time-out and a copy are never held
    assert strategy.relabel(batch) == [] and strategy.relabel(offered) == []
    m = strategy.metrics()
    assert m["relabel_held"] == held and m["relabel_gated_off"] == len(wrong) + len(offered)
    kept = {frames_key(ep) for ep in offered[-held:]}  # the newest, the rest dropped oldest first
    assert {frames_key(ep) for ep in strategy.held} == kept

    strategy.trainer.load_state_dict(opened_generator)
    assert strategy.trainer.gate_open
    released: list[Episode] = []
    calls = 0
    while strategy.held:
        before = len(strategy.held)
        new = wrong_picks(3, "train", seed=100 + calls)
        copies = strategy.relabel(new)
        calls += 1
        assert before - len(strategy.held) == min(HELD_RELEASE, before)  # a slice per call
        released += [c for c in copies if frames_key(c) in kept]
        assert len(copies) <= min(HELD_RELEASE, before) + len(new)
    assert calls == -(-held // HELD_RELEASE)
    # Nearly every held failure came back as a relabelled copy naming an object (some parse to nothing or
    # name the failed goal, and are dropped and counted as always).
    assert len(released) >= 0.85 * held
    check_copies(released, offered)
    assert all(parse(c.mission) is not None for c in released)
    assert strategy.metrics()["relabel_held"] == 0
    assert strategy.metrics()["relabels_made"] >= len(released)


def test_nothing_is_held_by_default_and_an_open_gate_holds_nothing():
    strategy = LearnedRelabel(GEN, seed=0)
    strategy.relabel(wrong_picks(20, "train", seed=1))
    assert strategy.metrics()["relabel_held"] == 0 and strategy.metrics()["relabel_gated_off"] == 20


def test_held_episodes_own_their_arrays():
    # Episodes as the relabeler receives them, decoded from a real message: one it holds must not keep that
    # whole message alive.
    cfg = make_config("higher", "small")
    collector = EpisodeCollector(cfg.world, 16, cfg.network.frame_stack, seed=2)
    rng = np.random.default_rng(2)
    sent: list[Episode] = []
    while len(relabel_candidates(sent)) < 10:
        sent += collector.step(rng.integers(0, 4, size=collector.n_envs))
    rejects: list[str] = []
    episodes = unpack_episodes(decode(encode("episodes", *pack_episodes(sent))), WorldSpec.of(cfg.world),
                               reject=rejects.append)
    assert not rejects and len(episodes) == len(sent)
    strategy = LearnedRelabel(GEN, seed=0, held_while_gated=10)
    strategy.relabel(episodes)
    assert len(strategy.held) == 10
    for ep in strategy.held:
        for value in fields_of(ep).values():
            if isinstance(value, np.ndarray):
                assert value.base is None, "a held array is a view of something else"


def test_many_episodes_travel_as_one_array_per_field():
    from higher_dist.learning.episode import episodes_from_state, episodes_state
    offered = wrong_picks(5, "train", seed=3)
    offered = [replace(ep, **{"frames": np.repeat(ep.frames[:1], n + 1, axis=0),
                          "actions": np.arange(n, dtype=np.uint8), "rewards": np.zeros(n, np.float32),
                          "weights_version": 10 * n, "actor_id": n % 2})
               for n, ep in zip((1, 7, 3, 12, 5), offered)]
    state = episodes_state(offered)
    assert state["frames"].shape[0] == sum(ep.frames.shape[0] for ep in offered)  # end to end, not a list
    back = episodes_from_state(state)
    for a, b in zip(back, offered):
        assert a.length == b.length and (a.weights_version, a.actor_id, a.pick_step) == (b.weights_version,
                                                                                           b.actor_id, b.pick_step)
        assert np.array_equal(a.frames, b.frames) and np.array_equal(a.mission, b.mission)
    assert episodes_from_state(episodes_state([])) == []


def test_held_episodes_survive_a_checkpoint(tmp_path):
    strategy = LearnedRelabel(GEN, seed=0, held_while_gated=50)
    offered = wrong_picks(30, "train", seed=21)
    strategy.relabel(offered)
    run_dir = RunDir(tmp_path)
    run_dir.save_checkpoint("relabeler", strategy.state_dict())  # torch.save, loaded with weights_only=True
    clone = LearnedRelabel(GEN, seed=0, held_while_gated=50)
    clone.load_state_dict(run_dir.load_checkpoint("relabeler"))
    assert len(clone.held) == len(offered)
    for a, b in zip(clone.held, offered):
        for key, value in fields_of(b).items():
            got = fields_of(a)[key]
            assert np.array_equal(got, value) if isinstance(value, np.ndarray) else got == value, key
    # A checkpoint from before held episodes existed loads with none held.
    old = strategy.state_dict()
    del old["held"]
    clone.load_state_dict(old)
    assert len(clone.held) == 0


def test_the_config_reaches_the_strategy_and_only_a_learned_one_may_hold():
    cfg = make_config("higher", "small", **{"relabel.held_while_gated": 64})
    assert make_relabel_strategy(cfg, seed=0).held.maxlen == 64
    for preset in ("her", "dqn", "noisy-her"):
        with pytest.raises(ValueError, match="relabel.held_while_gated"):
            make_config(preset, "small", **{"relabel.held_while_gated": 64})
    for bad in (-1, 10 ** 7, True, 2.5):
        with pytest.raises(ValueError, match="relabel.held_while_gated"):
            make_config("higher", "small", **{"relabel.held_while_gated": bad})
