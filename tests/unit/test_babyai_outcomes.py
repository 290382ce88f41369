"""Every outcome a BabyAI episode records, and the expert's description of it, checked against minigrid's own
verifiers on thousands of random episodes per family (go-to, open, pickup).

Each episode is replayed from a deep copy of its env taken right after its reset. The expert's sentence for
each recorded outcome is read back as text and turned into a fresh `GoToInstr` / `OpenInstr` / `PickupInstr`
of `ObjDesc(type, color, loc)` (loc: the location it names, on levels whose missions name one); stepped on
the replay as the level steps its own verifier, its first accepted step must be the recorded one.
Conversely every description the level's objects allow whose verifier accepts some step (a go-to only while
the object is in front) must have been recorded at its first such step (up to the first MAX_OUTCOMES).
Neither direction reads the world's own verifiers.
"""
from __future__ import annotations

import contextlib
import copy
import io
import re

import numpy as np
import pytest
from minigrid.envs.babyai.core.verifier import GoToInstr, ObjDesc, OpenInstr, PickupInstr

from higher_dist.config_presets import make_config
from higher_dist.world import babyai, babyai_language as lang
from higher_dist.world.babyai import BABYAI_ACTION_NAMES, BatchedBabyAI
from higher_dist.world.spec import MAX_LATER, MAX_OUTCOMES, RUNNING, SUCCESS, TIMEOUT, WorldSpec

PICKUP, DROP, TOGGLE = (BABYAI_ACTION_NAMES.index(a) for a in ("pickup", "drop", "toggle"))
INSTR = {"go to": GoToInstr, "open": OpenInstr, "pick up": PickupInstr}
VERB_OF_KIND = {"goto": "go to", "open": "open", "pickup": "pick up"}
SENTENCE = re.compile(r"(go to|open|pick up) (the|a) (\w+) (\w+)(?: (on your left|on your right|in front of you|behind you))?")
LOC_OF_PHRASE = dict(zip(lang.LOC_PHRASES, lang.LOCS))

# Random policies (left, right, forward, pickup, drop, toggle, done), biased towards the family's achieving
# action where it would act on something: toggle facing a closed door, pick up facing an object, drop while
# carrying. Go-to levels pick up and drop too: their verifiers then accept the empty cell an object was picked
# from, which is not recorded (nothing is in front). That never decides a go-to's step in these episodes:
# minigrid never starts the agent facing an object, so the object was in front, and recorded, before.
MOVES = [0.22, 0.22, 0.44, 0.04, 0.04, 0.02, 0.02]
ACT_P = {"goto": (PICKUP, 0.3), "open": (TOGGLE, 0.8), "pickup": (PICKUP, 0.6)}


def policy(env, kind: str, rng) -> int:
    front = env.grid.get(*env.front_pos)
    action, p = ACT_P[kind]
    acts_on = front is not None and (front.type == "door" and not front.is_open if kind == "open"
                                     else front.can_pickup() and env.carrying is None)
    if acts_on and rng.random() < p:
        return action
    if env.carrying is not None and front is None and rng.random() < 0.15:
        return DROP
    return int(rng.choice(len(MOVES), p=MOVES))


# (level, episodes, step limit, at least this many outcomes checked, at least this many episodes with 2+):
# step limits shorter than the levels' own give more episodes per step (the open levels' own, 576 steps,
# would give a handful); the minimums (about 2/3 of what the seeds give) keep the test from passing on
# episodes that achieve nothing. BabyAI-GoToObj-v0 has one object: its first go-to ends the episode.
LEVELS = [("BabyAI-GoToLocal-v0", 300, 40, 350, 100), ("BabyAI-GoToObj-v0", 200, 30, 40, 0),
          ("BabyAI-GoToRedBall-v0", 250, 30, 250, 80), ("BabyAI-OpenDoor-v0", 300, 40, 100, 4),
          ("BabyAI-OpenDoorLoc-v0", 300, 40, 100, 4), ("BabyAI-PickupDist-v0", 350, None, 250, 30),
          ("BabyAI-PickupLoc-v0", 300, 40, 200, 25)]


def run_episodes(level: str, n_episodes: int, max_steps: int | None, kind: str, seed: int):
    """n_episodes finished episodes of `level`: (env deep-copied at its reset, actions, the ending StepResult
    and the env's index in it). Every episode of every env counts: a finished env has been reset in place by
    `step`, and is copied before its next step."""
    batch = 16
    world = BatchedBabyAI(level, batch, env_seeds=[[seed, i] for i in range(batch)], max_steps=max_steps)
    world.reset()
    starts = [copy.deepcopy(env) for env in world.envs]
    actions: list[list[int]] = [[] for _ in range(batch)]
    rng = np.random.default_rng(seed)
    done = []
    while len(done) < n_episodes:
        step_actions = np.array([policy(env, kind, rng) for env in world.envs])
        result = world.step(step_actions)
        for i, a in enumerate(step_actions.tolist()):
            actions[i].append(a)
            if result.done[i]:
                done.append((starts[i], actions[i], result, i))
                starts[i], actions[i] = copy.deepcopy(world.envs[i]), []
    return done[:n_episodes]


def recorded_outcomes(result, i: int) -> list[tuple[int, tuple[int, ...]]]:
    """(step, attrs) of env i's outcomes, from picked/pick_step and later_*; asserts their -1 padding."""
    out = []
    if result.pick_step[i] < 0:
        assert (result.picked[i] == -1).all() and (result.later_step[i] == -1).all()
        assert (result.later_achieved[i] == -1).all()
        return out
    out.append((int(result.pick_step[i]), tuple(result.picked[i].tolist())))
    steps, later = result.later_step[i], result.later_achieved[i]
    n_later = int((steps >= 0).sum())
    assert (steps[:n_later] >= 0).all() and (steps[n_later:] == -1).all(), steps  # no gap in the list
    assert (later[n_later:] == -1).all() and (later[:n_later] >= 0).all()
    out += [(int(s), tuple(a)) for s, a in zip(steps[:n_later].tolist(), later[:n_later].tolist())]
    return out


def achieved_object(env, kind: str):
    return env.carrying if kind == "pickup" else env.grid.get(*env.front_pos)


def verifier_of(kind_verb: str, type_: str, color: str, loc: str | None, env):
    verifier = INSTR[kind_verb](ObjDesc(type_, color, loc))
    verifier.reset_verifier(env)
    return verifier


def check_episode(kind: str, start, actions, result, i: int, spec, tally, rng, cap: int = MAX_OUTCOMES) -> None:
    verb = VERB_OF_KIND[kind]
    recorded = recorded_outcomes(result, i)
    steps = [s for s, _ in recorded]
    assert steps == sorted(set(steps)), recorded  # in step order, one per step
    assert len({a[:2] for _, a in recorded}) == len(recorded), recorded  # distinct descriptions
    assert all(0 <= s < len(actions) for s in steps) and len(recorded) <= cap
    assert result.later_achieved.shape[1] == MAX_LATER == MAX_OUTCOMES - 1

    env = start
    # The replay needs the env's state and verifiers only: skipping the observation halves its cost.
    env.gen_obs = lambda: None
    with contextlib.redirect_stdout(io.StringIO()):
        # The expert's sentences, read as text: the verifier each one names (with the location it names on a
        # level that asks with locations), and its article at the reset (the level's for colour and type).
        described = []
        texts = [lang.decode(t) for t in spec.expert_tokens(np.array([a for _, a in recorded], ndmin=2), rng)]
        for (_, attrs), text in zip(recorded, texts):
            match = SENTENCE.fullmatch(text)
            assert match is not None and match[1] == verb, (text, kind)
            _, article, color, type_, phrase = match.groups()
            assert ObjDesc(type_, color).surface(env).split()[0] == article == lang.ARTICLES[attrs[3]], text
            assert (lang.COLORS.index(color), lang.TYPES.index(type_)) == attrs[:2]
            assert (phrase is not None) == (spec.has_locations and attrs[2] > 0), (text, attrs)
            tally["named_loc"] += phrase is not None
            described.append(verifier_of(verb, type_, color, LOC_OF_PHRASE.get(phrase), env))
        # Location mask: bit j set exactly when "VERB ... LOCS[j]" names the achieved object (its own verifier
        # accepts the outcome's step).
        located = [[verifier_of(verb, lang.TYPES[a[1]], lang.COLORS[a[0]], loc, env) for loc in lang.LOCS]
                   for _, a in recorded]
        # Every description the level's objects allow, for completeness.
        names = {lang.TYPES[t] for t in spec.language.types}
        every = {(c.color, c.type) for c in env.grid.grid if c is not None and c.type in names}
        complete = {d: verifier_of(verb, d[1], d[0], None, env) for d in every}
        first_text_success = [None] * len(recorded)
        first_success: dict[tuple[str, str], int] = {}
        for step, action in enumerate(actions):
            _, reward, terminated, truncated, _ = env.step(action)
            last = step == len(actions) - 1
            assert (terminated or truncated) == last, (step, len(actions))
            if action == DROP:  # as RoomGridLevel.step does for the level's own verifier
                for verifier in [*described, *complete.values(), *(v for row in located for v in row)]:
                    verifier.update_objs_poss()
            obj = achieved_object(env, kind)
            for k, verifier in enumerate(described):
                ok = verifier.verify(action) == "success"
                shown = kind != "goto" or (obj is not None and (obj.color, obj.type) == (
                    verifier.desc.color, verifier.desc.type))
                if ok and shown and first_text_success[k] is None:
                    first_text_success[k] = step
            for k, row in enumerate(located):
                hits = [v.verify(action) == "success" for v in row]
                if step == recorded[k][0]:
                    mask = sum(1 << j for j, hit in enumerate(hits) if hit)
                    assert mask == recorded[k][1][2], (recorded[k], mask)
                    tally["loc_bits"] += bin(mask).count("1")
            for d, verifier in complete.items():
                ok = verifier.verify(action) == "success"
                shown = kind != "goto" or (obj is not None and (obj.color, obj.type) == d)
                if ok and shown and d not in first_success:
                    first_success[d] = step
    # Each description's first accepted step is the step it was recorded at.
    assert first_text_success == steps, (recorded, first_text_success)
    # Nothing accepted is missing: the recorded list is every description by its first accepted step, capped.
    expected = sorted((s, (lang.COLORS.index(c), lang.TYPES.index(t))) for (c, t), s in first_success.items())
    assert [(s, a[:2]) for s, a in recorded] == expected[:cap], (recorded, expected)
    tally["capped"] += len(expected) > cap
    # The episode's own end: the level's verifier (in env.step) against the recorded outcome and reward.
    assert int(result.length[i]) == len(actions)
    assert result.outcome[i] == (SUCCESS if terminated else TIMEOUT) != RUNNING
    assert bool(result.terminated[i]) == terminated and bool(result.truncated[i]) == (truncated and not terminated)
    assert result.reward[i] == np.float32(reward)
    tally["outcomes"] += len(recorded)
    tally["multi"] += len(recorded) >= 2
    tally["success"] += bool(terminated)
    tally["timeout"] += not terminated


@pytest.mark.parametrize("level, n_episodes, max_steps, min_outcomes, min_multi", LEVELS,
                         ids=[row[0] for row in LEVELS])
def test_recorded_outcomes_are_exactly_what_minigrids_verifiers_accept(level, n_episodes, max_steps, min_outcomes,
                                                                        min_multi):
    spec = WorldSpec.of(make_config("her", level).world)
    kind = spec.level_kind
    seed = [row[0] for row in LEVELS].index(level)
    episodes = run_episodes(level, n_episodes, max_steps, kind, seed)
    tally = dict.fromkeys(("outcomes", "multi", "success", "timeout", "capped", "loc_bits", "named_loc"), 0)
    rng = np.random.default_rng(seed)
    for start, actions, result, i in episodes:
        check_episode(kind, start, actions, result, i, spec, tally, rng)
    assert len(episodes) == n_episodes
    assert tally["outcomes"] >= min_outcomes and tally["multi"] >= min_multi, tally
    assert tally["success"] >= 5 and tally["timeout"] >= 5, tally
    assert tally["loc_bits"] >= 1, tally
    # The expert names a location where the level's missions may (and one describes the object), else never.
    assert tally["named_loc"] >= tally["outcomes"] // 2 if spec.has_locations else tally["named_loc"] == 0, tally


def test_outcomes_beyond_the_cap_are_not_recorded(monkeypatch):
    """Random episodes never reach MAX_OUTCOMES distinct outcomes; with a cap of 2 they do, and only the
    first two (by step) are recorded."""
    monkeypatch.setattr(babyai, "MAX_OUTCOMES", 2)
    level = "BabyAI-GoToLocal-v0"
    spec = WorldSpec.of(make_config("her", level).world)
    tally = dict.fromkeys(("outcomes", "multi", "success", "timeout", "capped", "loc_bits", "named_loc"), 0)
    rng = np.random.default_rng(99)
    for start, actions, result, i in run_episodes(level, 100, 40, "goto", seed=99):
        check_episode("goto", start, actions, result, i, spec, tally, rng, cap=2)
    assert tally["capped"] >= 5 and tally["multi"] >= 20, tally
