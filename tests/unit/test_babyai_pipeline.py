"""A BabyAI pickup level through everything FetchAttr goes through: config, spec, collector, relabelling,
the wire's boundary checks (honest episodes pass, each lie is dropped under its reason, random damage never
crashes the receiver) and the learner's replay."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from higher_dist.config import ConfigError, GeneratorConfig
from higher_dist.config_presets import make_config
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode
from higher_dist.learning.hindsight.relabel import ExpertRelabel, LearnedRelabel, make_relabel_strategy
from higher_dist.learning.learner import Learner
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import WireError, decode, encode, pack_episodes, unpack_episodes
from higher_dist.world import babyai_language as lang
from higher_dist.world.spec import WorldSpec
from support.babyai_lies import LIES, lie

torch.set_num_threads(1)  # a test shares the machine; torch's default of every core spins under load

LEVEL = "BabyAI-PickupDist-v0"
CFG = make_config("her", LEVEL, **{"replay.min_size": 50, "replay.capacity": 20_000})
SPEC = WorldSpec.of(CFG.world)
EPISODES = real_episodes(CFG.world, 240, seed=3)
FAILED_PICKS = [ep for ep in EPISODES if ep.outcome == TIMEOUT and ep.pick_step >= 0]


def _unpack(episodes, spec=SPEC, **kw):
    rejects: list[str] = []
    back = unpack_episodes(decode(encode("episodes", *pack_episodes(episodes))), spec, reject=rejects.append, **kw)
    return back, rejects


def test_the_spec_comes_from_the_level():
    assert (SPEC.family, SPEC.view_size, SPEC.max_steps, SPEC.n_actions) == ("babyai", 7, 49, 7)
    assert SPEC.vocab_size == len(lang.VOCAB) and SPEC.mission_len == lang.MISSION_LEN and not SPEC.has_heldout
    assert SPEC.language is lang.PICKUP and CFG.frames == 1_000_000
    assert WorldSpec.of(make_config("her", "BabyAI-PickupLoc-v0").world).max_steps == 64
    assert WorldSpec.of(make_config("her", LEVEL, **{"world.max_steps": 30}).world).max_steps == 30


def test_levels_and_methods_that_do_not_fit_are_refused_by_name():
    with pytest.raises(ValueError, match="BabyAI-GoToSeq-v0.*not supported: supported are levels whose every "
                                         "mission is one non-strict 'pick up', 'go to' or 'open' instruction"):
        WorldSpec.of(make_config("her", "BabyAI-GoToSeq-v0").world)
    with pytest.raises(ConfigError, match="world.reward_shaping"):
        make_config("reward", LEVEL)
    with pytest.raises(ValueError, match="noisy"):
        make_relabel_strategy(make_config("noisy-her", LEVEL), seed=0)
    with pytest.raises(ConfigError, match="world: unknown world 'BabyAl'"):
        make_config("her", "BabyAl")


def test_a_random_policy_gives_every_kind_of_episode():
    outcomes = {(ep.outcome, ep.pick_step >= 0) for ep in EPISODES}
    assert {(SUCCESS, True), (TIMEOUT, True), (TIMEOUT, False)} <= outcomes
    assert all(ep.outcome != WRONG_PICK for ep in EPISODES)  # a wrong pickup never ends a BabyAI episode
    for ep in EPISODES:
        if ep.outcome == SUCCESS:  # the level's reward, on the last step only
            assert ep.rewards[-1] == pytest.approx(1 - 0.9 * ep.length / SPEC.max_steps, abs=1e-6)
            assert ep.actions[-1] == 3 and not ep.rewards[:-1].any()
        if ep.pick_step >= 0:  # the first pick: a pickup action with `picked` in front just before it
            assert ep.actions[ep.pick_step] == 3
            front = SPEC.front_object(ep.frames[ep.pick_step][None])[0]
            assert (front[:2] == ep.picked[:2]).all() and 0 <= ep.picked[2] < 16  # a location mask


@pytest.mark.parametrize("most", [1, 2, 4])
def test_the_expert_relabels_failures_at_up_to_max_per_episode_of_their_outcomes(most):
    strategy = ExpertRelabel(seed=0, spec=SPEC, max_per_episode=most)
    copies = strategy.relabel(EPISODES)
    expected = sum(min(ep.n_outcomes, most) for ep in FAILED_PICKS)
    assert len(copies) == expected > 10
    assert any(ep.n_outcomes > 1 for ep in FAILED_PICKS)  # the level records more than one pickup
    by_episode = iter(copies)
    for ep in FAILED_PICKS:
        steps = ep.outcome_steps()
        ends = []
        for _ in range(min(ep.n_outcomes, most)):
            copy = next(by_episode)
            assert copy.relabelled and copy.outcome == WRONG_PICK and copy.length - 1 in steps
            k = steps.index(copy.length - 1)
            ends.append(k)
            assert copy.frames.shape[0] == copy.length + 1 and (copy.frames == ep.frames[: copy.length + 1]).all()
            assert copy.rewards[-1] == pytest.approx(1 - 0.9 * copy.length / SPEC.max_steps, abs=1e-6)
            described = lang.parse(copy.mission)
            # "pick up the red ball": colour and type of that outcome's object, the article as the level would say
            truth = ep.outcome_attrs(k)
            assert described is not None and described[2] == -1
            assert (described[[0, 1, 3]] == truth[[0, 1, 3]]).all() and (copy.picked == truth).all()
            assert copy.n_outcomes == 1 and copy.pick_step == copy.length - 1
        assert len(set(ends)) == len(ends) and ends == sorted(ends)  # distinct outcomes, in step order
        assert not ep.relabelled and ep.outcome == TIMEOUT  # original untouched
    assert strategy.metrics()["relabel_accuracy"] == 1.0


def test_honest_episodes_and_their_copies_pass_the_boundary_and_fill_the_replay():
    episodes = real_episodes(CFG.world, 120, seed=4, relabelled=True)
    assert any(ep.relabelled for ep in episodes)
    back, rejects = _unpack(episodes, n_actors=1)
    assert rejects == [] and len(back) == len(episodes)
    assert all((a.pick_step, a.length) == (b.pick_step, b.length) for a, b in zip(back, episodes))
    core = Learner(CFG)
    core.add_episodes(back)
    assert len(core.replay) == sum(ep.length for ep in back)
    assert core.replay.composition()["relabelled"] > 0


@pytest.mark.parametrize("kind", LIES)
def test_each_lie_is_dropped_under_its_reason_and_the_rest_kept(kind):
    rng = np.random.default_rng(LIES.index(kind))
    bad, reason = lie(kind, EPISODES, SPEC, rng)
    honest = EPISODES[:5]
    back, rejects = _unpack(honest[:2] + [bad] + honest[2:])
    assert rejects == [reason] and len(back) == len(honest)


def test_a_relabelled_copy_from_an_actor_is_refused():
    copy = ExpertRelabel(spec=SPEC).relabel(FAILED_PICKS[:1])
    _, rejects = _unpack(copy, allow_relabelled=False)
    assert rejects == ["relabel_origin"]


def test_fetchattr_episodes_are_not_this_levels():
    fetch = real_episodes(make_config("her", "paper").world, 30, seed=0)
    back, rejects = _unpack(fetch)
    assert back == [] and len(rejects) == 30 and set(rejects) <= {"episode_length", "mission_token", "mission_grammar",
                                                                   "cell", "attribute", "outcome", "reward"}


def test_the_levels_actions_reach_a_fetchattr_run_only_as_a_reject():
    ep = next(e for e in real_episodes(make_config("her", "paper").world, 30, seed=0) if e.outcome == TIMEOUT)
    ep = replace(ep, actions=ep.actions.copy())
    ep.actions[0] = 5  # toggle: a BabyAI action, not FetchAttr's
    _, rejects = _unpack([ep], WorldSpec.of(make_config("her", "paper").world))
    assert rejects == ["action"]


_ARRAYS = ("frames", "actions", "rewards", "mission", "outcome", "picked", "goal", "pick_step", "relabelled")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(_ARRAYS), st.integers(0, 10_000), st.integers(-300, 300))
def test_random_damage_is_dropped_or_harmless(array_name, where, value):
    """Any one value of a real batch changed to anything: the receiver either refuses it (WireError, or
    a counted reject) or gets episodes its replay and relabeler take without raising."""
    fields, arrays = pack_episodes(EPISODES[:6] + ExpertRelabel(spec=SPEC).relabel(FAILED_PICKS[:2]))
    arr = arrays[array_name].copy()
    flat = arr.reshape(-1)
    info = np.iinfo(arr.dtype) if arr.dtype.kind in "iu" else None
    flat[where % flat.size] = value if info is None else np.clip(value, info.min, info.max)
    arrays[array_name] = arr
    try:
        frames = encode("episodes", fields, arrays)
        back = unpack_episodes(decode(frames), SPEC, reject=lambda reason: None)
    except WireError:
        return
    core = Learner(CFG)
    core.add_episodes(back)
    ExpertRelabel(spec=SPEC).relabel(back)


def test_the_generator_learns_from_the_levels_successes_and_describes_the_picks():
    small = GeneratorConfig(embed_dim=8, conv_channels=(16, 16), word_embed_dim=16, hidden=64, lr=3e-3,
                            batch_size=32, capacity=2000, n_min=50, min_accuracy=0.5, eval_every_updates=100)
    strategy = make_relabel_strategy(make_config("higher", LEVEL, generator=small), seed=0)
    assert isinstance(strategy, LearnedRelabel)
    successes = [ep for ep in EPISODES + real_episodes(CFG.world, 150, seed=7) if ep.outcome == SUCCESS]
    strategy.observe(successes)
    for _ in range(3):
        strategy.train(100)
    assert strategy.trainer.evaluations >= 1 and strategy.trainer.val_accuracy > 0.5, strategy.metrics()
    copies = strategy.relabel(FAILED_PICKS)
    assert copies and all(c.actions[-1] == 3 and c.rewards[-1] > 0 and c.relabelled for c in copies)
    assert strategy.metrics()["relabel_accuracy"] > 0.5
