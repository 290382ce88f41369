"""The boundary's outcome rules per BabyAI level kind (world/episode_rules.py, world/babyai_episodes.py), through
the wire as a receiver sees them: real episodes of a go-to, an open and a pickup level and their expert copies
(several per failure) all pass; each lie of tests/support/babyai_lies.py, made from one of them by editing
fields, is dropped under its own reason, and only it. A FetchAttr episode records one outcome at most."""
from __future__ import annotations

import functools
from dataclasses import fields, replace

import numpy as np
import pytest

from higher_dist.config_presets import make_config
from higher_dist.learning.episode import Episode
from higher_dist.learning.hindsight.relabel import make_relabel_strategy, relabel_candidates
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import codec
from higher_dist.wire.episodes import pack_episodes, unpack_episodes
from higher_dist.world.episode_rules import EPISODE_FAULTS
from higher_dist.world.spec import TIMEOUT, WRONG_PICK, WorldSpec
from support.babyai_lies import lie_from, lies_for

# Level -> how many real episodes: enough for failures with two or more outcomes (each lie about later
# outcomes needs one), few on the open level, whose random episodes run to 576 steps.
LEVELS = {"BabyAI-GoToLocal-v0": 90, "BabyAI-OpenDoorLoc-v0": 40, "BabyAI-PickupDist-v0": 150}
KIND = {"BabyAI-GoToLocal-v0": "goto", "BabyAI-OpenDoorLoc-v0": "open", "BabyAI-PickupDist-v0": "pickup"}
# The reason each lie must be dropped under; a dict where it depends on the level kind.
NOT_SHOWN = {"pickup": "picked_not_in_front", "goto": "reached_not_in_front", "open": "door_not_opened"}
REASON = {
    "short_timeout": "outcome", "success_reward": "reward", "pick_not_a_pickup": "outcome",
    "picked_elsewhere": NOT_SHOWN, "outcome_view_changed": NOT_SHOWN, "door_left_closed": "door_not_opened",
    "mission_not_the_goal": "mission_goal", "ungrammatical": "mission_grammar", "padding_channel": "cell",
    "plural_unset": "attribute", "picked_type_unnamed": "attribute",
    "later_swapped_with_first": "later_outcome", "later_repeats_first": "later_outcome",
    "later_repeats_another": "later_outcome", "later_gap": "later_outcome", "later_past_the_end": "later_outcome",
    "later_without_first": "later_outcome", "later_attrs_without_step": "attribute",
    "later_type_unnamed": "attribute", "later_location_unset": "attribute", "later_elsewhere": NOT_SHOWN,
    "later_not_an_achieving_action": "later_outcome",
    "copy_goes_on": "relabel_inconsistent", "copy_unrewarded": "reward",
    "copy_keeps_earlier_outcomes": "relabel_inconsistent",
}
# The fields each lie may change (the rest is the real episode it was made from).
LATER = {"later_achieved", "later_step"}
CHANGES = {
    "short_timeout": {"frames", "actions", "rewards"}, "success_reward": {"rewards"},
    "pick_not_a_pickup": {"actions"}, "picked_elsewhere": {"picked"}, "outcome_view_changed": {"frames"},
    "door_left_closed": {"frames"}, "mission_not_the_goal": {"mission"}, "ungrammatical": {"mission"},
    "padding_channel": {"frames"}, "plural_unset": {"goal"}, "picked_type_unnamed": {"picked"},
    "later_swapped_with_first": {"picked", "pick_step"} | LATER, "later_repeats_first": {"later_achieved"},
    "later_repeats_another": LATER, "later_gap": LATER, "later_past_the_end": {"later_step"},
    "later_without_first": {"picked", "pick_step"}, "later_attrs_without_step": {"later_achieved"},
    "later_type_unnamed": {"later_achieved"}, "later_location_unset": {"later_achieved"},
    "later_elsewhere": {"later_achieved"}, "later_not_an_achieving_action": {"actions"},
    "copy_goes_on": {"relabelled", "mission", "rewards"}, "copy_unrewarded": {"rewards"},
    "copy_keeps_earlier_outcomes": {"picked", "pick_step"} | LATER,
}
CASES = [(level, name) for level in LEVELS for name in lies_for(KIND[level])]


@functools.lru_cache(maxsize=None)
def _level(level: str):
    """(config, spec, real episodes, the run's expert copies of them), made once per level."""
    cfg = make_config("her", level)
    episodes = real_episodes(cfg.world, LEVELS[level], seed=3)
    return cfg, WorldSpec.of(cfg.world), episodes, make_relabel_strategy(cfg, 0).relabel(episodes)


def _through_the_wire(episodes: list[Episode], spec: WorldSpec) -> tuple[list[Episode], list[str]]:
    rejects: list[str] = []
    msg = codec.decode(codec.encode("episodes", *pack_episodes(episodes), sender="relabeler"))
    return unpack_episodes(msg, spec, reject=rejects.append), rejects


def _changed(a: Episode, b: Episode) -> set[str]:
    def same(x, y) -> bool:
        return np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
    return {f.name for f in fields(Episode) if not same(getattr(a, f.name), getattr(b, f.name))}


@pytest.mark.parametrize("level", LEVELS)
def test_honest_episodes_and_their_expert_copies_all_pass(level):
    cfg, spec, episodes, copies = _level(level)
    assert spec.level_kind == KIND[level]
    most = cfg.relabel.max_per_episode
    candidates = relabel_candidates(episodes)
    # A copy per outcome up to relabel.max_per_episode; some failures get several.
    assert len(copies) == sum(min(ep.n_outcomes, most) for ep in candidates) > len(candidates)
    back, rejects = _through_the_wire(episodes + copies, spec)
    assert rejects == [] and len(back) == len(episodes) + len(copies)
    for copy in back[len(episodes):]:
        assert copy.relabelled and copy.outcome == WRONG_PICK and copy.pick_step == copy.length - 1
        assert copy.n_outcomes == 1
    assert any(ep.n_outcomes > 1 for ep in back[:len(episodes)])  # later outcomes cross the wire


@pytest.mark.parametrize("level, name", CASES)
def test_each_lie_is_dropped_under_its_own_reason_and_only_it(level, name):
    cfg, spec, episodes, copies = _level(level)
    want = REASON[name] if isinstance(REASON[name], str) else REASON[name][KIND[level]]
    for seed in range(3):  # lies made from different real episodes
        bad, reason, source = lie_from(name, episodes, spec, np.random.default_rng(seed))
        assert reason == want
        changed = _changed(bad, source)
        assert changed and changed <= CHANGES[name], (name, changed)
        _, source_rejects = _through_the_wire([source], spec)
        assert source_rejects == []  # what it was made from is honest: the edit is the lie
        honest = episodes[:6] + copies[:3]
        back, rejects = _through_the_wire(honest[:4] + [bad] + honest[4:], spec)
        assert rejects == [want] and len(back) == len(honest), (name, seed)


def test_go_to_levels_have_no_achieving_action_and_only_open_levels_doors_to_close():
    assert not {"pick_not_a_pickup", "later_not_an_achieving_action"} & set(lies_for("goto"))
    assert "door_left_closed" in lies_for("open") and "door_left_closed" not in lies_for("pickup")
    with pytest.raises(ValueError, match="level kind 'putnext'"):
        lies_for("putnext")


def test_every_outcome_reason_is_produced_by_some_lie():
    produced = {REASON[name] if isinstance(REASON[name], str) else REASON[name][KIND[level]] for level, name in CASES}
    outcome_reasons = {"reached_not_in_front", "door_not_opened", "later_outcome", "picked_not_in_front",
                       "relabel_inconsistent", "attribute"}
    assert outcome_reasons <= set(EPISODE_FAULTS) and outcome_reasons <= produced


def test_a_fetchattr_episode_records_one_outcome_at_most():
    cfg = make_config("her", "paper")
    spec = WorldSpec.of(cfg.world)
    assert spec.max_outcomes == 1
    episodes = real_episodes(cfg.world, 30, seed=1)
    assert _through_the_wire(episodes, spec)[1] == []
    picked = next(ep for ep in episodes if ep.outcome == WRONG_PICK)
    nothing = next(ep for ep in episodes if ep.outcome == TIMEOUT)
    lies = []
    for ep, step in ((picked, picked.pick_step), (picked, max(picked.pick_step - 1, 0)), (nothing, 0)):
        later_achieved, later_step = ep.later_achieved.copy(), ep.later_step.copy()
        later_achieved[0], later_step[0] = picked.picked, step
        lies.append(replace(ep, later_achieved=later_achieved, later_step=later_step))
    back, rejects = _through_the_wire(lies, spec)
    assert back == [] and rejects == ["later_outcome"] * len(lies)
