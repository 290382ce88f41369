"""relabel.withheld_while_gated: the failures a learned relabeller cannot relabel yet are kept out of the
replay while its gate is shut, and the learner still counts them as played."""
from __future__ import annotations

import pytest
import torch
from test_relabel import GEN, mixed_batch, trained, wrong_picks  # noqa: F401 (a fixture)

from higher_dist.config_presets import make_config
from higher_dist.learning.agent import AgentBuilder
from higher_dist.learning.episode import WRONG_PICK, Withheld
from higher_dist.learning.hindsight.relabel import LearnedRelabel, make_relabel_strategy, relabel_batch
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.roles.relabeler import RelabelerService
from higher_dist.wire import codec
from higher_dist.wire.episodes import pack_episodes, unpack_episodes, withheld_in
from higher_dist.wire.sockets import RejectCounter
from higher_dist.world.spec import WorldSpec

torch.set_num_threads(1)


def test_while_shut_the_wrong_picks_are_kept_out_and_counted(trained):
    strategy = LearnedRelabel(GEN, seed=0, withheld_while_gated=True)
    batch, wrong = mixed_batch(seed=3)  # a success, a time-out and a copy stay in
    stored, withheld = relabel_batch(strategy, batch)
    assert [id(ep) for ep in stored] == [id(ep) for ep in batch if not any(ep is w for w in wrong)]
    assert withheld == Withheld(len(wrong), sum(ep.length for ep in wrong)) and withheld.episodes == 20
    m = strategy.metrics()
    assert m["relabel_withheld"] == m["relabel_gated_off"] == len(wrong)

    # Once the gate is open nothing is kept out: the originals go in beside their copies.
    strategy.trainer.load_state_dict(trained.trainer.state_dict())
    assert strategy.trainer.gate_open
    stored, withheld = relabel_batch(strategy, batch)
    assert withheld == Withheld() and all(any(ep is s for s in stored) for ep in batch)
    assert len(stored) > len(batch)  # and their copies
    assert strategy.metrics()["relabel_withheld"] == len(wrong)


def test_off_by_default_nothing_is_kept_out():
    strategy = LearnedRelabel(GEN, seed=0)
    batch, _ = mixed_batch(seed=4)
    stored, withheld = relabel_batch(strategy, batch)
    assert withheld == Withheld() and [id(e) for e in stored] == [id(e) for e in batch]
    assert strategy.metrics()["relabel_withheld"] == 0


def test_the_count_survives_a_checkpoint():
    strategy = LearnedRelabel(GEN, seed=0, withheld_while_gated=True)
    relabel_batch(strategy, wrong_picks(7, "train", seed=5))
    clone = LearnedRelabel(GEN, seed=0, withheld_while_gated=True)
    clone.load_state_dict(strategy.state_dict())
    assert clone.metrics()["relabel_withheld"] == 7
    old = strategy.state_dict()
    del old["withheld"]  # a checkpoint from before the option loads with none kept out
    clone.load_state_dict(old)
    assert clone.metrics()["relabel_withheld"] == 0


def test_the_config_reaches_the_strategy_and_only_a_learned_one_may_withhold():
    cfg = make_config("higher", "small", **{"relabel.withheld_while_gated": True})
    assert make_relabel_strategy(cfg, seed=0).withhold
    assert not make_relabel_strategy(make_config("higher", "small"), seed=0).withhold
    for preset in ("her", "dqn", "noisy-her"):
        with pytest.raises(ValueError, match="relabel.withheld_while_gated"):
            make_config(preset, "small", **{"relabel.withheld_while_gated": True})
    for bad in (1, "yes", 0.0):
        with pytest.raises(ValueError, match="relabel.withheld_while_gated"):
            make_config("higher", "small", **{"relabel.withheld_while_gated": bad})


def _service(**overrides) -> RelabelerService:
    cfg = make_config("higher", "small", actors=1, **{"relabel.withheld_while_gated": True, **overrides})
    return RelabelerService(AgentBuilder(cfg), RejectCounter())


def small_episodes(n: int, seed: int):
    """Real episodes of the small world under a random policy: successes, wrong picks, time-outs in turn."""
    return real_episodes(make_config("higher", "small").world, n, seed=seed)


def test_the_learner_counts_what_the_relabeler_kept_out_as_played():
    # The relabeler service's message, decoded as the learner decodes it, into a learner core: the frames,
    # episodes and replay-ratio inserts are those the actors played; the replay holds none of the failures.
    service = _service()
    spec = service.agent.spec
    core = service.agent.learner()
    played = 0
    for seed in (1, 2):  # batches of wrong picks only: nothing to store, no message yet
        batch = [ep for ep in small_episodes(30, seed) if ep.outcome == WRONG_PICK]
        played += sum(ep.length for ep in batch)
        assert service.relabel(batch) is None
    assert service.withheld_unsent.episodes > 0
    kept_out_before = service.withheld_unsent.episodes
    mixed = small_episodes(30, seed=9)
    played += sum(ep.length for ep in mixed)
    frames = service.relabel(mixed)
    assert frames is not None and service.withheld_unsent == Withheld()
    msg = codec.decode(frames)
    episodes = unpack_episodes(msg, spec, allow_relabelled=True, n_actors=1)
    withheld = withheld_in(msg)
    core.add_episodes(episodes, withheld)
    n_wrong = sum(ep.outcome == WRONG_PICK for ep in mixed)
    assert n_wrong > 0 and withheld.episodes == kept_out_before + n_wrong
    assert len(episodes) == len(mixed) - n_wrong
    assert core.frames == played and core.episodes == kept_out_before + len(mixed)
    assert core.limiter.inserted == played
    assert core.metrics()["replay_wrong_pick"] == 0


def test_withheld_counts_are_the_relabelers_and_must_add_up():
    spec = WorldSpec.of(make_config("higher", "small").world)
    eps = small_episodes(4, seed=0)
    for counts, sender_may, reason in ((Withheld(2, 30), False, "field"),  # an actor withholds nothing
                                       (Withheld(2, 1), True, "range"),  # fewer frames than episodes
                                       (Withheld(1, spec.max_steps + 1), True, "range")):  # longer than one may be
        fields, arrays = pack_episodes(eps, counts)
        msg = codec.decode(codec.encode("episodes", fields, arrays, sender="relabeler"))
        with pytest.raises(codec.WireError) as err:
            unpack_episodes(msg, spec, allow_relabelled=sender_may, n_actors=1)
        assert err.value.reason == reason
    fields, arrays = pack_episodes(eps, Withheld(2, 2 * spec.max_steps))
    msg = codec.decode(codec.encode("episodes", fields, arrays, sender="relabeler"))
    assert len(unpack_episodes(msg, spec, allow_relabelled=True, n_actors=1)) == 4
    assert withheld_in(msg) == Withheld(2, 2 * spec.max_steps)
    # Without the fields a message withholds nothing (the actors' messages, and older relabelers').
    fields, arrays = pack_episodes(eps)
    assert "withheld_frames" not in fields
    assert withheld_in(codec.decode(codec.encode("episodes", fields, arrays, sender="actor"))) == Withheld()
    with pytest.raises(codec.WireError):
        codec.encode("episodes", {**fields, "withheld_frames": -1}, arrays)


def test_the_single_process_runner_counts_what_it_kept_out():
    from higher_dist.learning.runner import SingleProcessRunner

    cfg = make_config("higher", "small", frames=1500, actors=1,
                      **{"relabel.withheld_while_gated": True, "replay.min_size": 100,
                         "replay.samples_per_insert": 0.5})
    runner = SingleProcessRunner(cfg)
    runner.run(frames=1500, metrics_every=1500)
    withheld = runner.relabeler.metrics()["relabel_withheld"]
    assert not runner.relabeler.gate_open and withheld > 0
    # The pace counts every finished original episode's frames: so does the learner, kept out or not.
    assert runner.core.frames == runner.pace.frames > 0
    assert runner.core.metrics()["replay_wrong_pick"] == 0
    # Training success counts the kept-out failures as the failures they were.
    assert runner.core.episodes == len(runner.core.recent_success) or len(runner.core.recent_success) == 1000
