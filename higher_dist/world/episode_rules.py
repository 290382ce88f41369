"""What an episode means on its world: whether a received episode is one the run's world could have
produced (or an honest relabelled copy of one), checked for a whole batch at once.

The wire (wire/episodes.py) first checks shapes, types and the run's ranges, then asks `episode_faults`
for the meaning. The rules every family shares live here (rewards before the last step are zero; the
achieved outcomes are distinct, in step order, each by the family's achieving action and shown by the
views; a relabelled copy ends at its one outcome; a mission is a sentence naming the goal); what differs
between families lives with each family and is reached through `family_rules`: `grid.FetchAttrEpisodes`
(a pick ends the episode) and `babyai_episodes.BabyAIEpisodes` (a wrong outcome goes on; the level's kind
says what an outcome is). Each rule's reason is one of `EPISODE_FAULTS`, the counter names the receiver
drops under.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from higher_dist.world.babyai_episodes import BABYAI_EPISODES
from higher_dist.world.grid import FETCHATTR_EPISODES
from higher_dist.world.spec import MAX_LATER, WRONG_PICK, WorldSpec

# Why an episode means something its world cannot have produced (counter names, one per rule).
EPISODE_FAULTS = (
    "attribute",  # a goal or picked attribute unnamed (-1) where this world always names it, or named where nothing was picked
    "cell",  # a view cell this world cannot show (an object without its attributes, a wall with a colour)
    "outcome",  # outcome inconsistent with length, the pick's step and action, picked or goal
    "reward",  # rewards inconsistent with outcome (or the shaping rule)
    "picked_not_in_front",  # the picked object is not in the cell in front before the pick
    "reached_not_in_front",  # a go-to level's reached object is not in front after the step that reached it
    "door_not_opened",  # an open level's door is not the one toggled, or not open after the toggle
    "later_outcome",  # outcomes after the first: out of step order, repeated, unset mid-list, or more than the world has
    "relabel_inconsistent",  # a relabelled copy that is not a wrong pick ending at its one outcome, or names its own goal
    "mission_grammar",  # not a sentence of the language (all-PAD, ungrammatical, an object this world lacks)
    "mission_goal",  # an original episode whose mission does not name its goal
)


@dataclass(frozen=True)
class EpisodeBatch:
    """N episodes as concatenated arrays (the wire's layout, wire/episodes.py), with the indices every
    rule needs. Per-episode fields are int64 (relabelled bool) so rules compare without overflow."""

    frames: np.ndarray  # (F, V, V, 4): every episode's T+1 frames, one after another
    actions: np.ndarray  # (S,): every episode's T steps
    rewards: np.ndarray  # (S,)
    lengths: np.ndarray  # (N,) T of each episode
    mission: np.ndarray  # (N, L)
    outcome: np.ndarray  # (N,)
    picked: np.ndarray  # (N, 4)
    goal: np.ndarray  # (N, 4)
    pick_step: np.ndarray  # (N,)
    later_achieved: np.ndarray  # (N, MAX_LATER, 4)
    later_step: np.ndarray  # (N, MAX_LATER)
    relabelled: np.ndarray  # (N,) bool
    starts: np.ndarray  # (N,) each episode's first step
    ends: np.ndarray  # (N,) one past each episode's last step
    frame_starts: np.ndarray  # (N,) each episode's first frame

    @classmethod
    def of(cls, arrays: Mapping[str, np.ndarray]) -> "EpisodeBatch":
        lengths = arrays["lengths"].astype(np.int64)
        ends = np.cumsum(lengths)
        starts = ends - lengths
        as64 = lambda name: arrays[name].astype(np.int64)  # noqa: E731
        return cls(frames=arrays["frames"], actions=arrays["actions"], rewards=arrays["rewards"], lengths=lengths,
                   mission=arrays["mission"], outcome=as64("outcome"), picked=as64("picked"), goal=as64("goal"),
                   pick_step=as64("pick_step"), later_achieved=as64("later_achieved"),
                   later_step=as64("later_step"), relabelled=arrays["relabelled"].astype(bool), starts=starts, ends=ends,
                   frame_starts=starts + np.arange(len(lengths)))

    @property
    def n(self) -> int:
        return len(self.lengths)

    def at(self, values: np.ndarray, index: np.ndarray) -> np.ndarray:
        """values[index] per episode, clipped into range and safe on empty arrays: a rule reads it only
        where an earlier rule has not already dropped the episode."""
        if not len(values):
            return np.zeros((self.n,) + values.shape[1:], values.dtype)
        return values[np.clip(index, 0, len(values) - 1)]

    def action_at(self, step: np.ndarray) -> np.ndarray:
        """Per episode, the action of its own step `step` (clipped into the episode), int64."""
        return self.at(self.actions, self.starts + self._within(step)).astype(np.int64)

    def frame_at(self, step: np.ndarray) -> np.ndarray:
        """Per episode, the frame before its own step `step` (clipped into the episode)."""
        return self.at(self.frames, self.frame_starts + self._within(step))

    def frame_after(self, step: np.ndarray) -> np.ndarray:
        """Per episode, the frame its own step `step` reached (clipped into the episode)."""
        return self.at(self.frames, self.frame_starts + self._within(step) + 1)

    def _within(self, step: np.ndarray) -> np.ndarray:
        return np.clip(step, 0, np.maximum(self.lengths - 1, 0))


def family_rules(spec: WorldSpec):
    """The rules of `spec`'s world family: an object with achieve_action, not_shown_reason, picks,
    outcome_attributes_ok, attributes_ok, cells_ok, shown, outcome_ok, reward and mission_ok (see
    grid.FetchAttrEpisodes). A success's reward on any family is
    `spec.pick_reward`."""
    return BABYAI_EPISODES if spec.family == "babyai" else FETCHATTR_EPISODES


def episode_faults(spec: WorldSpec, arrays: Mapping[str, np.ndarray], reasons: list[str]) -> None:
    """Fill `reasons[i]` (where still "") with the first of `EPISODE_FAULTS` episode i breaks.

    `arrays` hold a batch whose structure (view size, mission length, lengths adding up to the steps and
    frames) and ranges (vocabulary, actions, attribute and cell values, episode length) the caller has
    checked; an episode whose reason is already set is not parsed. Vectorised over the batch except the
    grammar, which parses each remaining mission once."""
    b = EpisodeBatch.of(arrays)
    rules = family_rules(spec)

    def flag(mask: np.ndarray, reason: str) -> None:
        for i in np.flatnonzero(mask):
            if not reasons[i]:
                reasons[i] = reason

    picks = rules.picks(spec, b)
    flag((b.pick_step >= b.lengths) | (b.pick_step < -1), "outcome")
    flag(~rules.attributes_ok(spec, b, picks), "attribute")
    cells = rules.cells_ok(spec, b.frames)
    if cells is not None:
        frame_bad = ~cells.reshape(len(b.frames), -1).all(axis=1)
        flag(np.add.reduceat(frame_bad, b.frame_starts) > 0 if b.n else frame_bad[:0], "cell")
    # Outcome versus length, the first outcome's action, the last action and the goal.
    action = rules.achieve_action(spec)
    if action is not None:
        flag(picks & (b.action_at(b.pick_step) != action), "outcome")
    flag(~rules.outcome_ok(spec, b, b.action_at(b.lengths - 1)), "outcome")
    _later_outcome_faults(spec, rules, b, picks, flag)
    # Rewards: zero before the last step; the last is the family's reward for the episode, a relabelled
    # copy's that of a success on its last step.
    early = np.ones(b.rewards.shape[0], dtype=bool)
    early[(b.ends - 1)[b.ends >= 1]] = False
    step_episode = np.repeat(np.arange(b.n), b.lengths) if b.n else np.zeros(0, np.int64)
    flag(np.bincount(step_episode[early & (b.rewards != 0)], minlength=b.n) > 0, "reward")
    expected = np.where(b.relabelled, spec.pick_reward(b.lengths), rules.reward(spec, b))
    flag(np.abs(b.at(b.rewards, b.ends - 1) - expected) > 1e-5, "reward")
    # Each outcome is shown by the views (the picked object in front before the pick, ...).
    flag(picks & ~rules.shown(spec, b, b.pick_step, b.picked), rules.not_shown_reason(spec))
    for k in range(MAX_LATER):
        step = b.later_step[:, k]
        flag((step >= 0) & ~rules.shown(spec, b, step, b.later_achieved[:, k]), rules.not_shown_reason(spec))
    # A copy ends at its one outcome: nothing after it.
    has_later = (b.later_step >= 0).any(axis=1)
    flag(b.relabelled & ((b.outcome != WRONG_PICK) | (b.pick_step != b.lengths - 1) | has_later),
         "relabel_inconsistent")
    # The grammar last: the only per-episode Python loop, skipped for episodes already dropped.
    parse = spec.language.parse
    for i in range(b.n):
        if reasons[i]:
            continue
        named = parse(b.mission[i])
        if named is None or not rules.mission_ok(spec, named):
            reasons[i] = "mission_grammar"
        elif b.relabelled[i] and (named.astype(np.int64) == b.goal[i]).all():
            reasons[i] = "relabel_inconsistent"  # it would store the failed goal as reached
        elif not b.relabelled[i] and not (named.astype(np.int64) == b.goal[i]).all():
            reasons[i] = "mission_goal"


def _later_outcome_faults(spec: WorldSpec, rules, b: EpisodeBatch, picks: np.ndarray, flag) -> None:
    """Outcomes after the first: set ones come first, in increasing steps after the first outcome and within
    the episode, each by the achieving action, with attributes exactly where a step is set, no two with
    one description (each is the first step a description was achieved), no more than the world records."""
    step, attrs = b.later_step, b.later_achieved
    n_later = (step >= 0).sum(axis=1)
    prefix = (step >= 0) == (np.arange(MAX_LATER)[None, :] < n_later[:, None])
    steps = np.concatenate([b.pick_step[:, None], step], axis=1)
    rising = np.where(step >= 0, step > steps[:, :-1], True).all(axis=1)
    flag(~prefix.all(axis=1) | ~rising | (step >= b.lengths[:, None]).any(axis=1) | ((n_later > 0) & ~picks)
         | (n_later + 1 > spec.max_outcomes), "later_outcome")
    flat = attrs.reshape(-1, 4)
    set_ok = rules.outcome_attributes_ok(spec, flat).reshape(step.shape)
    unset_ok = (attrs == -1).all(axis=2)
    flag(~np.where(step >= 0, set_ok, unset_ok).all(axis=1), "attribute")
    action = rules.achieve_action(spec)
    for k in range(MAX_LATER):
        on = step[:, k] >= 0
        if action is not None:
            flag(on & (b.action_at(step[:, k]) != action), "later_outcome")
        for j in range(k):  # the same description twice
            flag(on & (attrs[:, j, :2] == attrs[:, k, :2]).all(axis=1), "later_outcome")
        flag(on & (b.picked[:, :2] == attrs[:, k, :2]).all(axis=1), "later_outcome")
