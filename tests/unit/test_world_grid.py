"""The batched gridworld: movement, view, picks, limits, rewards, resets, seeding and errors."""
from dataclasses import replace

import numpy as np
import pytest

from higher_dist.config import WorldConfig
from higher_dist.config_presets import small_world
from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK
from higher_dist.world.grid import (KIND_BALL, KIND_EMPTY, KIND_KEY, KIND_UNSEEN, KIND_WALL, RUNNING,
                                    BatchedFetchAttr, cell_attrs, object_cells)
from higher_dist.world.objects import ObjectSpace

LEFT, RIGHT, FORWARD, PICK = 0, 1, 2, 3
UP, EAST, DOWN, WEST = 0, 1, 2, 3
RED_KEY = (0, 0, 2, 2)  # red key, neutral, medium
GREEN_BALL = (1, 1, 2, 2)
BLUE_BALL_DARK_TINY = (2, 1, 3, 0)


def make_env(cfg=None, batch_size=1, seed=0, **kwargs):
    env = BatchedFetchAttr(cfg or WorldConfig(), batch_size, seed=seed, **kwargs)
    env.reset()
    return env


def act(env, action):
    return env.step(np.array([action] * env.batch_size))


# ------------------------------------------------------------------------------- movement


def test_forward_moves_one_cell_in_each_direction():
    env = make_env()
    expected = {UP: (4, 5), EAST: (5, 6), DOWN: (6, 5), WEST: (5, 4)}
    for direction, target in expected.items():
        env.set_state(0, (5, 5), direction, [], RED_KEY)
        act(env, FORWARD)
        assert tuple(env.agent_pos[0]) == target
        assert env.agent_dir[0] == direction


def test_turning_left_and_right_cycles_directions_without_moving():
    env = make_env()
    env.set_state(0, (5, 5), UP, [], RED_KEY)
    seen = []
    for _ in range(4):
        act(env, RIGHT)
        seen.append(int(env.agent_dir[0]))
    assert seen == [EAST, DOWN, WEST, UP]
    seen = []
    for _ in range(4):
        act(env, LEFT)
        seen.append(int(env.agent_dir[0]))
    assert seen == [WEST, DOWN, EAST, UP]
    assert tuple(env.agent_pos[0]) == (5, 5)


@pytest.mark.parametrize("start,direction", [((1, 4), UP), ((4, 10), EAST), ((10, 4), DOWN), ((4, 1), WEST)])
def test_walls_block_forward(start, direction):
    env = make_env()
    env.set_state(0, start, direction, [], RED_KEY)
    result = act(env, FORWARD)
    assert tuple(env.agent_pos[0]) == start
    assert not result.done[0]


def test_objects_block_forward_and_the_agent_walks_around_them():
    env = make_env()
    env.set_state(0, (5, 5), UP, [((4, 5), GREEN_BALL)], RED_KEY)
    act(env, FORWARD)
    assert tuple(env.agent_pos[0]) == (5, 5)
    act(env, RIGHT), act(env, FORWARD), act(env, LEFT), act(env, FORWARD), act(env, FORWARD)
    assert tuple(env.agent_pos[0]) == (3, 6)


# ----------------------------------------------------------------------------------- view


def reference_view(room: np.ndarray, agent, direction, size=7):
    """Independent per-direction reference: view cell (i, j) is `ahead` cells forward and `side`
    cells to the agent's right, written out for each heading."""
    out = np.zeros((size, size, 4), dtype=np.uint8)
    r, c = agent
    for i in range(size):
        for j in range(size):
            ahead, side = size - 1 - i, j - size // 2
            rr, cc = {UP: (r - ahead, c + side), EAST: (r + side, c + ahead),
                      DOWN: (r + ahead, c - side), WEST: (r - side, c - ahead)}[direction]
            if 0 <= rr < room.shape[0] and 0 <= cc < room.shape[1]:
                out[i, j] = room[rr, cc]
    return out


@pytest.mark.parametrize("direction", [UP, EAST, DOWN, WEST])
def test_view_cell_by_cell_on_a_hand_made_layout(direction):
    env = make_env()
    objects = [((2, 3), RED_KEY), ((4, 4), GREEN_BALL), ((3, 1), BLUE_BALL_DARK_TINY), ((6, 3), GREEN_BALL)]
    env.set_state(0, (3, 3), direction, objects, RED_KEY)
    view = env.view()[0]
    # The room as the world should hold it, built by hand.
    room = np.zeros((12, 12, 4), dtype=np.uint8)
    room[:, :, 0] = KIND_EMPTY
    room[0, :, 0] = room[-1, :, 0] = room[:, 0, 0] = room[:, -1, 0] = KIND_WALL
    for (r, c), (color, kind, shade, size) in objects:
        room[r, c] = (KIND_KEY + kind, color + 1, shade + 1, size + 1)
    np.testing.assert_array_equal(env.room_cells(0), room)
    np.testing.assert_array_equal(view, reference_view(room, (3, 3), direction))
    # A few cells written out by hand, to pin the orientation itself.
    assert tuple(view[6, 3]) == (KIND_EMPTY, 0, 0, 0)  # the agent's own cell: what lies under it
    if direction == UP:
        assert tuple(view[5, 3]) == (KIND_KEY, 1, 3, 3)  # red key just ahead
        assert tuple(view[6, 1]) == (KIND_BALL, 3, 4, 1)  # blue ball two to the left
        assert tuple(view[3, 2]) == (KIND_WALL, 0, 0, 0)  # top wall, three ahead, one left
        assert tuple(view[2, 3]) == (KIND_UNSEEN, 0, 0, 0)  # beyond the wall: outside the grid
        assert tuple(view[5, 4]) == (KIND_EMPTY, 0, 0, 0)
    elif direction == EAST:
        assert tuple(view[5, 4]) == (KIND_BALL, 2, 3, 3)  # green ball ahead-right at (4, 4)
        assert tuple(view[6, 0]) == (KIND_WALL, 0, 0, 0)  # top wall, three to the left
        assert tuple(view[0, 3]) == (KIND_EMPTY, 0, 0, 0)  # (3, 9): six ahead, inside the room
    elif direction == DOWN:
        assert tuple(view[3, 3]) == (KIND_BALL, 2, 3, 3)  # green ball three ahead at (6, 3)
        assert tuple(view[6, 5]) == (KIND_BALL, 3, 4, 1)  # blue ball two to the right
        assert tuple(view[6, 6]) == (KIND_WALL, 0, 0, 0)  # left wall column, three to the right
    else:
        assert tuple(view[4, 3]) == (KIND_BALL, 3, 4, 1)  # blue ball two ahead
        assert tuple(view[3, 3]) == (KIND_WALL, 0, 0, 0)
        assert tuple(view[2, 3]) == (KIND_UNSEEN, 0, 0, 0)
        assert tuple(view[6, 4]) == (KIND_KEY, 1, 3, 3)  # red key at (2, 3): north is the agent's right
        assert tuple(view[6, 0]) == (KIND_BALL, 2, 3, 3)  # green ball at (6, 3): three to the left
        assert (view[:, :, 0] == KIND_BALL).sum() == 2  # the green ball at (4, 4) is behind: unseen


def test_view_shape_dtype_and_nothing_behind_the_agent():
    env = make_env()
    env.set_state(0, (5, 5), UP, [((6, 5), GREEN_BALL)], RED_KEY)  # directly behind
    view = env.view()
    assert view.shape == (1, 7, 7, 4) and view.dtype == np.uint8
    assert not (view[0, :, :, 0] == KIND_BALL).any()


def test_cell_codes_round_trip_for_every_object():
    objects = ObjectSpace(WorldConfig()).all_objects
    np.testing.assert_array_equal(cell_attrs(object_cells(objects)), objects)


# ---------------------------------------------------------------------------------- picks


def test_pick_on_the_goal_succeeds_and_any_matching_copy_counts():
    env = make_env()
    env.set_state(0, (5, 5), UP, [((4, 5), RED_KEY), ((8, 8), RED_KEY), ((2, 2), GREEN_BALL)], RED_KEY)
    mission = env.mission[0].copy()
    result = act(env, PICK)
    assert result.terminated[0] and not result.truncated[0]
    assert result.reward[0] == 1.0 and result.outcome[0] == SUCCESS
    np.testing.assert_array_equal(result.picked[0], RED_KEY)
    np.testing.assert_array_equal(result.goal[0], RED_KEY)
    np.testing.assert_array_equal(result.mission_done[0], mission)
    assert result.length[0] == 1


def test_pick_on_a_wrong_object_ends_with_zero_reward():
    env = make_env()
    env.set_state(0, (5, 5), EAST, [((5, 6), GREEN_BALL), ((1, 1), RED_KEY)], RED_KEY)
    act(env, LEFT), act(env, RIGHT)
    result = act(env, PICK)
    assert result.terminated[0] and result.outcome[0] == WRONG_PICK and result.reward[0] == 0.0
    np.testing.assert_array_equal(result.picked[0], GREEN_BALL)
    assert result.length[0] == 3


def test_pick_on_an_empty_cell_or_wall_does_nothing():
    env = make_env()
    env.set_state(0, (1, 5), DOWN, [((5, 5), GREEN_BALL)], GREEN_BALL)
    before = env.view().copy()
    result = act(env, PICK)
    assert not result.done[0] and result.outcome[0] == RUNNING and result.reward[0] == 0
    assert (result.picked[0] == -1).all()
    np.testing.assert_array_equal(result.view, before)
    act(env, RIGHT), act(env, RIGHT)  # now facing the wall
    result = act(env, PICK)
    assert not result.done[0] and tuple(env.agent_pos[0]) == (1, 5)


def test_shaped_reward_is_a_quarter_per_matching_attribute():
    cfg = replace(WorldConfig(), reward_shaping=True)
    goal = (2, 1, 3, 0)  # blue ball, dark, tiny
    candidates = {0.0: (0, 0, 0, 1), 0.25: (2, 0, 0, 1), 0.5: (2, 1, 0, 1), 0.75: (2, 1, 3, 1), 1.0: goal}
    env = make_env(cfg)
    for expected, picked in candidates.items():
        env.set_state(0, (5, 5), UP, [((4, 5), picked)], goal)
        result = act(env, PICK)
        assert result.reward[0] == pytest.approx(expected)
        assert result.outcome[0] == (SUCCESS if expected == 1.0 else WRONG_PICK)
    # Without shaping a 3-of-4 match is worth nothing.
    env = make_env()
    env.set_state(0, (5, 5), UP, [((4, 5), candidates[0.75])], goal)
    assert act(env, PICK).reward[0] == 0.0


# ---------------------------------------------------------------------- limit and resets


def test_truncation_at_the_step_limit_is_a_time_out_not_a_terminal():
    cfg = replace(WorldConfig(), max_steps=5)
    env = make_env(cfg)
    env.set_state(0, (5, 5), UP, [((8, 8), RED_KEY)], RED_KEY)
    for step in range(1, 5):
        result = act(env, LEFT)
        assert not result.done[0] and result.length[0] == step
    result = act(env, LEFT)
    assert result.truncated[0] and not result.terminated[0]
    assert result.outcome[0] == TIMEOUT and result.length[0] == 5 and result.reward[0] == 0
    assert (result.picked[0] == -1).all()
    assert env.steps[0] == 0  # a new episode started in place


def test_a_pick_on_the_last_step_is_terminal_not_truncated():
    env = make_env(replace(WorldConfig(), max_steps=2))
    env.set_state(0, (5, 5), WEST, [((4, 5), GREEN_BALL)], RED_KEY)
    assert not act(env, RIGHT).done[0]  # now facing the ball
    result = act(env, PICK)  # the second and last step
    assert result.terminated[0] and not result.truncated[0] and result.outcome[0] == WRONG_PICK


def test_auto_reset_gives_the_new_episode_and_keeps_the_final_view():
    env = make_env(batch_size=2)
    env.set_state(0, (5, 5), UP, [((4, 5), RED_KEY)], RED_KEY)
    env.set_state(1, (5, 5), UP, [((4, 5), RED_KEY)], RED_KEY)
    before_mission = env.mission.copy()
    result = env.step(np.array([PICK, LEFT]))
    assert result.done.tolist() == [True, False]
    assert result.final_view[0, 5, 3, 0] == KIND_KEY  # what the pick saw
    np.testing.assert_array_equal(result.view[0], env.view()[0])  # the new episode's first view
    np.testing.assert_array_equal(result.view[1], result.final_view[1])
    np.testing.assert_array_equal(result.mission_done, before_mission)
    np.testing.assert_array_equal(result.mission[1], before_mission[1])
    assert env.steps.tolist() == [0, 1]
    # Arrays handed out are never edited by later steps.
    saved = {k: getattr(result, k).copy() for k in ("view", "mission", "goal", "mission_done", "final_dir")}
    rng = np.random.default_rng(0)
    for _ in range(100):
        env.step(rng.integers(4, size=2))
    for key, value in saved.items():
        np.testing.assert_array_equal(getattr(result, key), value)


def test_final_direction_is_the_one_reached_before_the_reset():
    env = make_env(small_world(), batch_size=8, seed=2)
    rng = np.random.default_rng(4)
    finished = 0
    for _ in range(300):
        actions = rng.integers(4, size=8)
        before = env.agent_dir
        result = env.step(actions)
        expected = (before + np.select([actions == LEFT, actions == RIGHT], [-1, 1], 0)) % 4
        np.testing.assert_array_equal(result.final_dir, expected)
        finished += int(result.done.sum())
    assert finished > 20


def test_reset_places_objects_from_the_split_and_the_goal_among_them():
    cfg = WorldConfig()
    space = ObjectSpace(cfg)
    for goal_set, allowed in (("train", space.train_objects), ("heldout", space.heldout_objects)):
        env = make_env(cfg, batch_size=16, seed=5, goal_set=goal_set)
        allowed_set = {tuple(o) for o in allowed.tolist()}
        directions = set()
        for _ in range(3):
            for i in range(16):
                room = env.room_cells(i)
                is_object = room[:, :, 0] >= KIND_KEY
                assert is_object.sum() == cfg.n_objects
                placed = {tuple(a) for a in cell_attrs(room[is_object].copy().view("<u4").ravel()).tolist()}
                assert placed <= allowed_set
                assert tuple(env.goal[i].tolist()) in placed
                r, c = env.agent_pos[i]
                assert room[r, c, 0] == KIND_EMPTY and 1 <= r <= 10 and 1 <= c <= 10
                directions.add(int(env.agent_dir[i]))
            env.reset()
        assert directions == {0, 1, 2, 3}


# ------------------------------------------------------------------ seeding and batching


def run_random(env, n_steps, seed):
    rng = np.random.default_rng(seed)
    out = [env.reset()]
    for _ in range(n_steps):
        r = env.step(rng.integers(4, size=env.batch_size))
        out.append((r.view, r.mission, r.reward, r.outcome, r.length, r.picked, r.goal, r.final_view))
    return out


def test_same_seed_same_run_and_different_seed_different_run():
    cfg = small_world()
    a = run_random(BatchedFetchAttr(cfg, 4, seed=7), 200, seed=1)
    b = run_random(BatchedFetchAttr(cfg, 4, seed=7), 200, seed=1)
    c = run_random(BatchedFetchAttr(cfg, 4, seed=8), 200, seed=1)
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            np.testing.assert_array_equal(u, v)
    assert any(not np.array_equal(x[0], y[0]) for x, y in zip(a, c))


def test_a_batch_steps_like_single_envs_seeded_by_the_same_scheme():
    cfg, batch, seed = WorldConfig(), 6, 11
    rng = np.random.default_rng(3)
    actions = rng.integers(4, size=(300, batch))
    together = BatchedFetchAttr(cfg, batch, seed=seed)
    alone = [BatchedFetchAttr(cfg, 1, env_seeds=[[seed, i]]) for i in range(batch)]
    v, m = together.reset()
    for i, env in enumerate(alone):
        vi, mi = env.reset()
        np.testing.assert_array_equal(vi[0], v[i]), np.testing.assert_array_equal(mi[0], m[i])
    finished = 0
    for row in actions:
        r = together.step(row)
        finished += int(r.done.sum())
        for i, env in enumerate(alone):
            ri = env.step(row[i: i + 1])
            for name in ("view", "mission", "reward", "terminated", "truncated", "final_view", "outcome",
                         "length", "picked", "goal", "mission_done", "final_dir"):
                np.testing.assert_array_equal(getattr(ri, name)[0], getattr(r, name)[i], err_msg=name)
    assert finished > 20  # the comparison went through many resets


def test_reset_with_a_seed_reseeds_every_env():
    env = BatchedFetchAttr(small_world(), 3, seed=0)
    first = env.reset(seed=42)
    env.reset()
    again = env.reset(seed=42)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])


# -------------------------------------------------------------------------------- errors


@pytest.mark.parametrize("actions,match", [
    (np.array([0.0, 1.0]), "integers"),
    (np.array([True, False]), "integers"),
    (np.array([0, 1, 2]), "shape"),
    (np.array([[0, 1]]), "shape"),
    (np.array([0, 4]), "0..3"),
    (np.array([-1, 0]), "0..3"),
    (["a", "b"], "integers"),
])
def test_invalid_actions_raise_a_clear_error(actions, match):
    env = make_env(small_world(), batch_size=2)
    with pytest.raises(ValueError, match=match):
        env.step(actions)


def test_step_before_reset_is_refused():
    with pytest.raises(RuntimeError, match="reset"):
        BatchedFetchAttr(small_world(), 1).step(np.array([0]))


@pytest.mark.parametrize("overrides,match", [
    (dict(room_size=3, n_objects=9), "do not fit"),
    (dict(room_size=1), "room_size"),
    (dict(n_objects=0), "n_objects"),
    (dict(max_steps=0), "max_steps"),
    (dict(view_size=4), "view_size"),
    (dict(colors=("red", "pink")), "unknown values"),
    (dict(shades=()), "at least one"),
    (dict(heldout_count=3), "heldout_count"),  # fewer held-out objects than the six colors
    (dict(heldout_count=300), "heldout_count"),
])
def test_invalid_configs_raise_a_clear_error(overrides, match):
    with pytest.raises(ValueError, match=match):
        BatchedFetchAttr(replace(WorldConfig(), **overrides), 1)


def test_invalid_constructor_arguments_raise():
    with pytest.raises(ValueError, match="goal_set"):
        BatchedFetchAttr(WorldConfig(), 1, goal_set="test")
    with pytest.raises(ValueError, match="batch_size"):
        BatchedFetchAttr(WorldConfig(), 0)
    with pytest.raises(ValueError, match="env_seeds"):
        BatchedFetchAttr(WorldConfig(), 2, env_seeds=[1])
    env = make_env()
    with pytest.raises(ValueError, match="outside the room or taken"):
        env.set_state(0, (0, 5), UP, [], RED_KEY)
    with pytest.raises(ValueError, match="outside the room or taken"):
        env.set_state(0, (5, 5), UP, [((5, 5), RED_KEY)], RED_KEY)
