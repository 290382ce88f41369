"""BabyAI pickup levels: level facts, batched stepping against minigrid itself, first-pickup
bookkeeping, and the pickup language (round trip, refusals, expert, every mission the levels say)."""
import contextlib
import io

import gymnasium as gym
import numpy as np
import pytest
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX

from higher_dist.world import babyai_language as lang
from higher_dist.world.babyai import (ACTION_PICKUP, BABYAI_ACTION_NAMES, CHANNEL_VALUES, BatchedBabyAI,
                                      is_pickup_level, level_facts, pickup_levels)
from higher_dist.world.spec import RUNNING, SUCCESS, TIMEOUT

# Forward and pickup often, so that pickups, successes and time-outs all happen within a few hundred steps.
ACTION_P = np.array([0.15, 0.15, 0.35, 0.25, 0.05, 0.03, 0.02])


def quiet():
    return contextlib.redirect_stdout(io.StringIO())


# ------------------------------------------------------------------------------------ level facts

def test_level_facts_and_pickup_levels():
    facts = level_facts("BabyAI-PickupDist-v0")
    assert (facts.view_size, facts.max_steps, facts.n_actions) == (7, 49, 7)
    assert not facts.has_locations
    assert level_facts("BabyAI-PickupLoc-v0").has_locations
    # Levels that are not level generators are probed: OpenDoorLoc always names a location, OpenDoor sometimes.
    assert level_facts("BabyAI-OpenDoorLoc-v0").has_locations and level_facts("BabyAI-OpenDoor-v0").has_locations
    assert not level_facts("BabyAI-OpenDoorColor-v0").has_locations and not level_facts("BabyAI-GoToLocal-v0").has_locations
    levels = pickup_levels()
    for name in ("BabyAI-PickupDist-v0", "BabyAI-Pickup-v0", "BabyAI-PickupLoc-v0", "BabyAI-UnblockPickup-v0",
                 "BabyAI-PickupAbove-v0", "BabyAI-UnlockPickup-v0"):
        assert name in levels and is_pickup_level(name)
    # Strict variants end on a wrong pickup; level generators mixing instruction kinds are not pickup-only.
    for name in ("BabyAI-PickupDistDebug-v0", "BabyAI-GoToRedBall-v0", "BabyAI-BossLevel-v0", "BabyAI-Synth-v0"):
        assert not is_pickup_level(name)
    assert len(BABYAI_ACTION_NAMES) == 7 and BABYAI_ACTION_NAMES[ACTION_PICKUP] == "pickup"
    assert CHANNEL_VALUES == (len(OBJECT_TO_IDX), len(COLOR_TO_IDX), 3, 1)


@pytest.mark.parametrize("name", ["BabyAI-GoToSeq-v0", "BabyAI-PutNextLocal-v0", "BabyAI-ActionObjDoor-v0",
                                  "BabyAI-OpenDoorDebug-v0", "BabyAI-NoSuchLevel-v0"])
def test_unsupported_and_unknown_levels_are_refused_by_name(name):
    with pytest.raises(ValueError, match=name) as error:
        level_facts(name)
    assert "BabyAI-PickupDist-v0" in str(error.value)  # lists the levels that would do
    with pytest.raises(ValueError, match=name):
        BatchedBabyAI(name, 2)


def test_bad_actions_and_batch_size_are_refused():
    world = BatchedBabyAI("BabyAI-PickupDist-v0", 2)
    with pytest.raises(RuntimeError, match="reset"):
        world.step([0, 0])
    world.reset()
    for bad, word in (([0, 7], "0..6"), ([0, -1], "0..6"), ([0.0, 1.0], "integers"), ([0, 1, 2], "shape")):
        with pytest.raises(ValueError, match=word):
            world.step(np.array(bad))
    with pytest.raises(ValueError, match="batch_size"):
        BatchedBabyAI("BabyAI-PickupDist-v0", 0)


# ------------------------------------------------------------------- batched = minigrid one by one

@pytest.mark.parametrize("level", ["BabyAI-PickupDist-v0", "BabyAI-PickupLoc-v0"])
def test_batched_steps_equal_minigrid_stepped_one_by_one(level):
    batch, seed, n_steps = 4, 7, 300
    world = BatchedBabyAI(level, batch, seed=seed)
    refs = [gym.make(level) for _ in range(batch)]
    with quiet():
        ref_obs = [ref.reset(seed=int(np.random.default_rng([seed, i]).integers(2**63 - 1)))[0]
                   for i, ref in enumerate(refs)]
    view, mission = world.reset()
    assert view.shape == (batch, 7, 7, 4) and view.dtype == np.uint8 and mission.dtype == np.int64
    assert (view[..., 3] == 0).all()
    for i in range(batch):
        assert (view[i, ..., :3] == ref_obs[i]["image"].transpose(1, 0, 2)).all()
        assert lang.decode(mission[i]) == ref_obs[i]["mission"]
    rng = np.random.default_rng(0)
    outcomes = set()
    for _ in range(n_steps):
        actions = rng.choice(7, size=batch, p=ACTION_P)
        before = world.mission
        result = world.step(actions)
        assert (result.mission_done == before).all()
        for i, ref in enumerate(refs):
            obs, reward, terminated, truncated, _ = ref.step(int(actions[i]))
            assert (result.final_view[i, ..., :3] == obs["image"].transpose(1, 0, 2)).all()
            assert result.reward[i] == np.float32(reward)
            assert result.terminated[i] == terminated
            assert result.truncated[i] == (truncated and not terminated)  # a success on the last step wins
            assert result.final_dir[i] == ref.unwrapped.agent_dir
            goal = lang.parse(result.mission_done[i])
            assert goal is not None and (result.goal[i] == goal).all()
            if terminated or truncated:
                assert result.outcome[i] == (SUCCESS if terminated else TIMEOUT)
                outcomes.add(int(result.outcome[i]))
                with quiet():
                    obs, _ = ref.reset()
            else:
                assert result.outcome[i] == RUNNING
            assert (result.view[i, ..., :3] == obs["image"].transpose(1, 0, 2)).all()
            assert lang.decode(result.mission[i]) == obs["mission"]
        assert (result.view[..., 3] == 0).all()
    assert outcomes == {SUCCESS, TIMEOUT}  # the walk crossed episode boundaries of both kinds


def test_max_steps_overrides_the_levels_limit():
    world = BatchedBabyAI("BabyAI-PickupDist-v0", 2, seed=1, max_steps=5)
    assert world.max_steps == 5 and world.envs[0].max_steps == 5
    world.reset()
    for _ in range(5):
        result = world.step(np.zeros(2, dtype=np.int64))  # turning never succeeds
    assert result.truncated.all() and (result.outcome == TIMEOUT).all() and (result.length == 5).all()
    assert (world.steps == 0).all()
    with pytest.raises(ValueError, match="max_steps"):
        BatchedBabyAI("BabyAI-PickupDist-v0", 2, max_steps=0)


def test_env_seeds_choose_each_envs_stream():
    a = BatchedBabyAI("BabyAI-PickupDist-v0", 3, seed=5)
    b = BatchedBabyAI("BabyAI-PickupDist-v0", 1, env_seeds=[[5, 2]])
    view_a, mission_a = a.reset()
    view_b, mission_b = b.reset()
    assert (view_a[2] == view_b[0]).all() and (mission_a[2] == mission_b[0]).all()


# ---------------------------------------------------------------------------- picks and successes

def _pick_candidate(env):
    """(color, type, -1, plural) of the object in front if a pickup now would take it, else None;
    plural counted independently of the adapter (another object with its colour and type)."""
    obj = env.grid.get(*env.front_pos)
    if env.carrying is not None or obj is None or not obj.can_pickup():
        return None
    same = [c for c in env.grid.grid if c is not None and c.type == obj.type and c.color == obj.color]
    return [lang.COLORS.index(obj.color), lang.TYPES.index(obj.type), -1, int(len(same) > 1)], obj


def test_first_pickup_is_reported_and_a_wrong_one_does_not_end_the_episode():
    """A policy that picks up the first object it faces, drops it if it is not wanted and then picks
    up only wanted ones: episodes with a wrong first pickup go on, keep reporting that first pickup
    (not the later one), and may still end in a success."""
    world = BatchedBabyAI("BabyAI-PickupDist-v0", 1, seed=3)
    world.reset()
    env = world.envs[0]
    rng = np.random.default_rng(1)
    wrong_first, late_successes, successes, carried_seen, second_picks = 0, 0, 0, 0, 0
    first = None  # (attrs, step) of this episode's first pickup, tracked by the test
    for _ in range(3000):
        candidate = _pick_candidate(env)
        wanted = candidate is not None and any(candidate[1] is w for w in env.instrs.desc.obj_set)
        if candidate is not None and (first is None or wanted):
            action = ACTION_PICKUP
        elif env.carrying is not None and env.grid.get(*env.front_pos) is None:
            action = 4  # drop
        else:
            action = int(rng.choice(3, p=[0.25, 0.25, 0.5]))
        if action != ACTION_PICKUP:
            candidate = None
        step_index = int(world.steps[0])
        result = world.step(np.array([action]))
        if candidate is not None:
            if first is None:
                first = (candidate[0], step_index)
                wrong_first += not wanted
            else:
                second_picks += 1
            if wanted:
                assert result.terminated[0] and result.outcome[0] == SUCCESS
                length = int(result.length[0])
                assert length == step_index + 1
                assert result.reward[0] == np.float32(1 - 0.9 * length / world.max_steps)
                successes += 1
                late_successes += first[1] < step_index  # after an earlier, wrong, pickup
            elif not result.done[0]:
                assert result.outcome[0] == RUNNING and result.reward[0] == 0
                # Minigrid draws the carried object in the agent's own cell: row V-1, column V//2.
                obj = candidate[1]
                assert result.final_view[0, 6, 3, :3].tolist() == [OBJECT_TO_IDX[obj.type], COLOR_TO_IDX[obj.color], 0]
                carried_seen += 1
        if first is None:
            assert (result.picked[0] == -1).all() and result.pick_step[0] == -1
        else:
            picked = result.picked[0].tolist()  # the third column: the object's location mask, 0..15
            assert picked[:2] + picked[3:] == first[0][:2] + first[0][3:] and 0 <= picked[2] < 16
            assert result.pick_step[0] == first[1]
        if result.done[0]:
            first = None
    assert wrong_first >= 3 and successes >= 3 and late_successes >= 1 and carried_seen >= 5
    assert second_picks >= 1


def test_step_arrays_handed_out_are_never_edited():
    world = BatchedBabyAI("BabyAI-PickupDist-v0", 4, seed=2)
    world.reset()
    rng = np.random.default_rng(0)
    kept = []
    for _ in range(200):
        r = world.step(rng.choice(7, size=4, p=ACTION_P))
        kept.append((r, r.picked.copy(), r.pick_step.copy(), r.mission.copy(), r.goal.copy(), r.view.copy()))
    for r, picked, pick_step, mission, goal, view in kept:
        assert (r.picked == picked).all() and (r.pick_step == pick_step).all()
        assert (r.mission == mission).all() and (r.goal == goal).all() and (r.view == view).all()


# ------------------------------------------------------------------------------------- language

def test_vocabulary_is_fixed_with_the_same_markers():
    from higher_dist.world import language
    assert (lang.PAD, lang.BEG, lang.END) == (language.PAD, language.BEG, language.END) == (0, 1, 2)
    assert lang.MISSION_LEN == 10 and len(set(lang.VOCAB)) == len(lang.VOCAB)
    assert lang.VOCAB[3:7] == ("pick", "up", "the", "a")
    assert lang.COLORS == tuple(COLOR_TO_IDX)  # minigrid's colour order
    assert len(lang.encode("pick up the purple ball in front of you").nonzero()[0]) == 9


def test_round_trip_for_every_sentence_of_the_grammar():
    attrs = lang.all_attrs()
    assert len(attrs) == 7 * 4 * 5 * 2
    tokens = lang.mission_tokens(attrs)
    assert tokens.shape == (len(attrs), lang.MISSION_LEN) and tokens.dtype == np.int64
    texts = set()
    for row, t, marked in zip(attrs, tokens, lang.with_markers(tokens)):
        text = lang.decode(t)
        texts.add(text)
        assert (lang.encode(text) == t).all()
        assert (lang.parse(t) == row).all() and (lang.parse(text) == row).all() and (lang.parse(marked) == row).all()
        assert lang.parse(t).dtype == np.int8
        assert lang.decode(marked) == text and lang.describe(row, None) == text
    assert len(texts) == len(attrs)
    parsed, ok = lang.parse_many(tokens)
    assert ok.all() and (parsed == attrs).all() and parsed.dtype == np.int64
    assert "pick up a red object" in texts and "pick up the grey key behind you" in texts
    assert "pick up the ball on your left" in texts and "pick up a box in front of you" in texts


@pytest.mark.parametrize("text", [
    "pick up red the ball", "pick up red ball", "up pick the ball", "pick up the ball red", "pick up the",
    "pick up the red", "pick up the ball on your", "pick up the ball in front of", "pick up the ball behind",
    "pick up the the ball", "pick up the red blue ball", "pick up the ball you behind", "pick the ball",
    "pick up a key on your left please", "", "pick up the ball ball", "pick up the object object"])
def test_parse_refuses_ungrammatical_sentences(text):
    assert lang.parse(text) is None


def test_parse_refuses_malformed_token_rows():
    good = lang.encode("pick up the red ball")
    after_pad = good.copy()
    after_pad[-1] = lang.WORD_TO_ID["ball"]  # a word after the padding
    out_of_range = good.copy()
    out_of_range[2] = len(lang.VOCAB)
    negative = good.copy()
    negative[0] = -3
    for bad in (after_pad, out_of_range, negative, good.astype(np.float32)):
        assert lang.parse(bad) is None
    attrs, ok = lang.parse_many(np.stack([good, after_pad, out_of_range]))
    assert ok.tolist() == [True, False, False] and (attrs[1:] == -1).all()
    with pytest.raises(ValueError, match="token ids"):
        lang.decode(out_of_range)
    with pytest.raises(ValueError, match="'pink'"):
        lang.encode("pick up the pink ball")
    with pytest.raises(ValueError, match="MISSION_LEN"):
        lang.encode("pick up the red ball " * 3)


def test_expert_names_colour_and_type_with_the_levels_article():
    red, ball = lang.COLORS.index("red"), lang.TYPES.index("ball")
    picked = np.array([[red, ball, -1, 0], [red, ball, -1, 1], [red, ball, 2, 0]], dtype=np.int8)
    texts = [lang.decode(t) for t in lang.expert_tokens(picked, np.random.default_rng(0))]
    assert texts == ["pick up the red ball", "pick up a red ball", "pick up the red ball"]


@pytest.mark.parametrize("level", pickup_levels())
def test_every_mission_a_level_says_parses_to_its_description(level):
    """The level's missions parse, and the parse is what minigrid's ObjDesc describes. The levels with
    the varied grammar (articles, "object", locations) get 200 seeds; the rest, whose missions come
    from a few fixed forms, 40, so that the file stays fast."""
    seeds = 200 if level in ("BabyAI-PickupDist-v0", "BabyAI-PickupLoc-v0") else 40
    env = gym.make(level).unwrapped
    world = BatchedBabyAI(level, 1)
    for seed in range(seeds):
        with quiet():
            env.reset(seed=seed)
        desc = env.instrs.desc
        expected = [lang.COLORS.index(desc.color) if desc.color else -1,
                    lang.TYPES.index(desc.type) if desc.type else -1,
                    lang.LOCS.index(desc.loc) if desc.loc else -1, int(len(desc.obj_set) > 1)]
        assert lang.parse(env.mission).tolist() == expected, env.mission
        tokens, goal = world._encode_mission(env.mission)
        assert lang.decode(tokens) == env.mission and goal.tolist() == expected
