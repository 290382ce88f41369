"""Lies a peer could tell about a BabyAI level's episodes, each made from a real episode of the level by
editing fields (the rest is the real episode): what the receiver must drop, and under which reason
(higher_dist/wire/episodes.py, world/episode_rules.py). The level's kind (pickup, go-to, open) says which
lies exist there (a go-to has no achieving action to fake) and which reason an outcome the views do not show
is dropped under. Used by the unit tests of the boundary and by the fuzz test of real learner and relabeler
processes on a level."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from higher_dist.learning.episode import SUCCESS, TIMEOUT, Episode
from higher_dist.world import babyai_language as lang
from higher_dist.world.spec import BABYAI_ACTION_NAMES, WorldSpec

# Lies about an original episode (any sender), and about a relabelled copy (only the relabeler may send one).
ORIGINAL_LIES = (
    "short_timeout", "success_reward", "pick_not_a_pickup", "picked_elsewhere", "outcome_view_changed",
    "door_left_closed", "mission_not_the_goal", "ungrammatical", "padding_channel", "plural_unset",
    "picked_type_unnamed", "later_swapped_with_first", "later_repeats_first", "later_repeats_another", "later_gap",
    "later_past_the_end", "later_without_first", "later_attrs_without_step", "later_type_unnamed",
    "later_location_unset", "later_elsewhere", "later_not_an_achieving_action")
COPY_LIES = ("copy_goes_on", "copy_unrewarded", "copy_keeps_earlier_outcomes")
ALL_LIES = ORIGINAL_LIES + COPY_LIES
# Lies that need the kind's achieving action (a go-to is reached by any step), or an open level's doors.
_ACTION_LIES = ("pick_not_a_pickup", "later_not_an_achieving_action")
_OPEN_LIES = ("door_left_closed",)
# Why the views do not show an outcome, per level kind; a type each kind's instructions never name.
NOT_SHOWN = {"pickup": "picked_not_in_front", "goto": "reached_not_in_front", "open": "door_not_opened"}
_UNNAMED_TYPE = {"pickup": lang.DOOR, "goto": -1, "open": lang.TYPES.index("key")}
_FORWARD = BABYAI_ACTION_NAMES.index("forward")  # never what picks up or opens
_ACHIEVING = {"pickup": BABYAI_ACTION_NAMES.index("pickup"), "open": BABYAI_ACTION_NAMES.index("toggle")}
_DOOR_CLOSED = 1


def lies_for(level_kind: str) -> tuple[str, ...]:
    """The lies a peer can tell about episodes of a level of `level_kind`."""
    if level_kind not in NOT_SHOWN:
        raise ValueError(f"lies_for: level kind {level_kind!r} is not one of {', '.join(NOT_SHOWN)}")
    return tuple(name for name in ALL_LIES if not (level_kind == "goto" and name in _ACTION_LIES)
                 and not (level_kind != "open" and name in _OPEN_LIES))


LIES = lies_for("pickup")  # the lies about a pickup level, such as BabyAI-PickupDist-v0


def lie(kind: str, episodes: list[Episode], spec: WorldSpec, rng: np.random.Generator) -> tuple[Episode, str]:
    """One episode of `episodes` (real ones of the level) made wrong in one way, `kind` (one of
    `lies_for(spec.level_kind)`), and the reason the receiver must drop it under."""
    bad, reason, _ = lie_from(kind, episodes, spec, rng)
    return bad, reason


def _clone(ep: Episode, **changes) -> Episode:
    """A copy of `ep` owning every array (so editing it leaves `ep` as it was), with `changes`."""
    fresh = {name: getattr(ep, name).copy() for name in
             ("frames", "actions", "rewards", "mission", "picked", "goal", "later_achieved", "later_step")}
    return replace(ep, **{**fresh, **changes})


def _pick(pool: list[Episode], what: str, kind: str, rng: np.random.Generator) -> Episode:
    if not pool:
        raise ValueError(f"lie {kind!r}: the episodes given hold no {what}; pass more real episodes of the level")
    return pool[int(rng.integers(len(pool)))]


def _other_colour(ep: Episode, k: int) -> int:
    """A colour for outcome `k` of `ep` that its object does not have and that gives no other outcome's
    description (so the only fault is the colour)."""
    colour, type_ = (int(v) for v in ep.outcome_attrs(k)[:2])
    taken = {tuple(int(v) for v in ep.outcome_attrs(j)[:2]) for j in range(ep.n_outcomes)}
    others = [(colour + shift) % len(lang.COLORS) for shift in range(1, len(lang.COLORS))]
    return next(c for c in others if (c, type_) not in taken)


def lie_from(kind: str, episodes: list[Episode], spec: WorldSpec,
             rng: np.random.Generator) -> tuple[Episode, str, Episode]:
    """As `lie`, with the real episode the lie was made from (what it differs from)."""
    if kind not in lies_for(spec.level_kind):
        raise KeyError(f"lie {kind!r} is not one of the lies about a {spec.level_kind} level: "
                       f"{', '.join(lies_for(spec.level_kind))}")
    originals = [ep for ep in episodes if not ep.relabelled]
    failures = [ep for ep in originals if ep.outcome == TIMEOUT and ep.pick_step >= 0]
    roomy = [ep for ep in failures if ep.n_outcomes <= 7]  # room for one more outcome in later_step
    several = [ep for ep in roomy if ep.n_outcomes >= 2]
    not_shown = NOT_SHOWN[spec.level_kind]
    if kind in ("success_reward", "mission_not_the_goal", "ungrammatical", "padding_channel", "plural_unset"):
        src = _pick([ep for ep in originals if ep.outcome == SUCCESS], "success", kind, rng)
    elif kind == "later_repeats_another":  # three outcomes, or two with steps left after the second
        src = _pick([ep for ep in several if ep.n_outcomes >= 3] or
                    [ep for ep in several if ep.later_step[0] < ep.length - 1], "failure with two outcomes", kind, rng)
    elif kind == "later_attrs_without_step":
        src = _pick(roomy, "failure that achieved an outcome", kind, rng)
    elif kind.startswith("later_") or kind == "copy_keeps_earlier_outcomes":
        src = _pick(several, "failure with two or more outcomes", kind, rng)
    else:
        src = _pick(failures, "failure that achieved an outcome", kind, rng)
    ep = _clone(src)
    front = (spec.view_size - 2, spec.view_size // 2)  # the cell in front of the agent in a view
    n_later = src.n_outcomes - 1

    if kind == "short_timeout":
        return _clone(src, frames=src.frames[:-1], actions=src.actions[:-1], rewards=src.rewards[:-1]), "outcome", src
    if kind == "success_reward":
        ep.rewards[-1] = 1.0
        return ep, "reward", src
    if kind == "pick_not_a_pickup":  # the first outcome's step is not a pickup / toggle
        ep.actions[ep.pick_step] = _FORWARD
        return ep, "outcome", src
    if kind == "picked_elsewhere":  # an object of another colour than the one in front (not the toggled door)
        ep.picked[0] = _other_colour(src, 0)
        return ep, not_shown, src
    if kind == "outcome_view_changed":  # the view that shows the first outcome shows another colour there
        view = ep.frames[ep.pick_step + spec.outcome_view_offset]
        view[front + (1,)] = (int(view[front + (1,)]) + 1) % len(lang.COLORS)
        return ep, not_shown, src
    if kind == "door_left_closed":  # the toggled door is closed after the toggle
        ep.frames[ep.pick_step + 1][front + (2,)] = _DOOR_CLOSED
        return ep, "door_not_opened", src
    if kind == "mission_not_the_goal":
        other = np.array([[(src.goal[0] + 1) % len(lang.COLORS), *src.goal[1:3], src.goal[3]]])
        return _clone(src, mission=spec.language.mission_tokens(other)[0]), "mission_goal", src
    if kind == "ungrammatical":
        ep.mission[:3] = ep.mission[[1, 0, 2]]  # "up pick the ...", "to go a ...", "the open red ..."
        return ep, "mission_grammar", src
    if kind == "padding_channel":
        ep.frames[0, 0, 0, 3] = 1  # the fourth channel of a BabyAI view is always 0
        return ep, "cell", src
    if kind == "plural_unset":
        ep.goal[3] = -1
        return ep, "attribute", src
    if kind == "picked_type_unnamed":
        ep.picked[1] = _UNNAMED_TYPE[spec.level_kind]
        return ep, "attribute", src
    if kind == "later_swapped_with_first":  # the second outcome recorded first: steps out of order
        ep.picked, ep.later_achieved[0] = src.later_achieved[0].copy(), src.picked.copy()
        ep.pick_step, ep.later_step[0] = int(src.later_step[0]), src.pick_step
        return ep, "later_outcome", src
    if kind == "later_repeats_first":
        ep.later_achieved[0, :2] = src.picked[:2]
        return ep, "later_outcome", src
    if kind == "later_repeats_another":
        if n_later >= 2:
            ep.later_achieved[1, :2] = src.later_achieved[0, :2]
        else:  # one more outcome after the second, with its description, on an achieving step where one is
            after = np.arange(src.later_step[0] + 1, src.length)
            action = _ACHIEVING.get(spec.level_kind)
            achieving = after[src.actions[after] == action] if action is not None else after
            ep.later_step[1] = int((achieving if len(achieving) else after)[0])
            ep.later_achieved[1] = src.later_achieved[0]
        return ep, "later_outcome", src
    if kind == "later_gap":  # -1, then the later outcomes
        ep.later_step[1:], ep.later_achieved[1:] = src.later_step[:-1], src.later_achieved[:-1]
        ep.later_step[0], ep.later_achieved[0] = -1, -1
        return ep, "later_outcome", src
    if kind == "later_past_the_end":
        ep.later_step[n_later - 1] = src.length
        return ep, "later_outcome", src
    if kind == "later_without_first":
        return _clone(src, picked=np.full(4, -1, np.int8), pick_step=-1), "later_outcome", src
    if kind == "later_attrs_without_step":  # an unset slot that names an object
        ep.later_achieved[n_later] = src.picked
        return ep, "attribute", src
    if kind == "later_type_unnamed":
        ep.later_achieved[0, 1] = _UNNAMED_TYPE[spec.level_kind]
        return ep, "attribute", src
    if kind == "later_location_unset":
        ep.later_achieved[0, 2] = -1
        return ep, "attribute", src
    if kind == "later_elsewhere":
        ep.later_achieved[0, 0] = _other_colour(src, 1)
        return ep, not_shown, src
    if kind == "later_not_an_achieving_action":
        ep.actions[ep.later_step[0]] = _FORWARD
        return ep, "later_outcome", src
    # A relabelled copy: of the failure's first outcome, or of its second.
    if kind == "copy_goes_on":  # it keeps the steps after its outcome, rewarded at the end
        copy = _copy_of(src, 0, spec)
        ep = _clone(src, relabelled=True, mission=copy.mission)
        ep.rewards[-1] = spec.pick_reward(ep.length)
        return ep, "relabel_inconsistent", src
    if kind == "copy_unrewarded":
        src = _copy_of(src, 0, spec)
        ep = _clone(src)
        ep.rewards[-1] = 0.0
        return ep, "reward", src
    if kind == "copy_keeps_earlier_outcomes":  # a copy ending at the second outcome that records the first too
        src = _copy_of(src, 1, spec)
        first = ep  # the failure it was made from
        ep = _clone(src, picked=first.picked.copy(), pick_step=first.pick_step)
        ep.later_achieved[0], ep.later_step[0] = src.picked, src.pick_step
        return ep, "relabel_inconsistent", src
    raise KeyError(kind)


def _copy_of(failed: Episode, k: int, spec: WorldSpec) -> Episode:
    """The expert's honest relabelled copy of `failed` ending at its outcome `k`."""
    mission = spec.language.expert_tokens(failed.outcome_attrs(k)[None])[0]
    return failed.relabel(mission, float(spec.pick_reward(failed.outcome_steps()[k] + 1)), outcome=k)
