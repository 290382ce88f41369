"""The Gymnasium view of the batched world, its registration and the optional gymnasium import."""
import subprocess
import sys

import numpy as np
import pytest

import higher_dist  # noqa: F401  registers the ids
from higher_dist.config_presets import small_world
from higher_dist.learning.episode import SUCCESS
from higher_dist.world import language
from higher_dist.world.grid import BatchedFetchAttr
from higher_dist.world.gym_env import FetchAttrEnv

gymnasium = pytest.importorskip("gymnasium")


def test_gymnasium_make_gives_both_worlds():
    paper = gymnasium.make("HIGhER/FetchAttr-v0")
    small = gymnasium.make("HIGhER/FetchAttr-Small-v0")
    assert paper.unwrapped.world_cfg.name == "paper" and paper.unwrapped.world_cfg.room_size == 10
    assert small.unwrapped.world_cfg.name == "small" and small.unwrapped.world_cfg.room_size == 5
    for env in (paper, small):
        obs, info = env.reset(seed=3)
        assert obs in env.observation_space and env.action_space.n == 4
        assert obs["image"].shape == (7, 7, 4) and obs["image"].dtype == np.uint8
        assert language.parse(obs["mission"]) is not None
        obs, reward, terminated, truncated, info = env.step(2)
        assert obs in env.observation_space and isinstance(reward, float)
        assert isinstance(terminated, bool) and isinstance(truncated, bool)
        env.close()


def test_passes_gymnasiums_env_checker():
    from gymnasium.utils.env_checker import check_env
    check_env(FetchAttrEnv("small"), skip_render_check=True)


def test_reset_with_a_seed_is_deterministic():
    env = FetchAttrEnv()
    a, _ = env.reset(seed=5)
    b, _ = env.reset(seed=5)
    np.testing.assert_array_equal(a["image"], b["image"])
    assert a["mission"] == b["mission"] and a["direction"] == b["direction"]


def test_episodes_end_cleanly_and_match_the_batched_world():
    """Terminal steps report the final observation; the next reset() starts the episode that env 0 of
    a batched world with the same seed starts; stepping past the end without reset() is refused."""
    env = FetchAttrEnv(small_world())
    batched = BatchedFetchAttr(small_world(), 1, seed=4)
    obs, _ = env.reset(seed=4)
    view, mission = batched.reset()
    rng = np.random.default_rng(0)
    episodes = outcomes = 0
    for _ in range(400):
        action = int(rng.integers(4))
        obs, reward, terminated, truncated, info = env.step(action)
        r = batched.step(np.array([action]))
        np.testing.assert_array_equal(obs["image"], r.final_view[0])
        assert obs["mission"] == language.decode(r.mission_done[0])
        assert obs["direction"] == r.final_dir[0] and reward == r.reward[0]
        assert (terminated, truncated) == (bool(r.terminated[0]), bool(r.truncated[0]))
        if terminated or truncated:
            episodes += 1
            outcomes += info["outcome"] == SUCCESS
            np.testing.assert_array_equal(info["goal"], r.goal[0])
            with pytest.raises(RuntimeError, match="reset"):
                env.step(0)
            obs, _ = env.reset()
            np.testing.assert_array_equal(obs["image"], r.view[0])
            assert obs["mission"] == language.decode(r.mission[0])
    assert episodes >= 10


def test_invalid_actions_raise_a_clear_error():
    env = FetchAttrEnv("small")
    env.reset(seed=0)
    for bad in (4, -1, 1.5, [0, 1], True):
        with pytest.raises(ValueError):
            env.step(bad)
    env.step(np.int64(1))  # numpy integers are fine


def run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)


def test_import_higher_dist_alone_registers_the_ids():
    done = run_python("import higher_dist, gymnasium; "
                      "print(sorted(i for i in gymnasium.registry if i.startswith('HIGhER/')))")
    assert done.returncode == 0, done.stderr
    assert "HIGhER/FetchAttr-Small-v0" in done.stdout and "HIGhER/FetchAttr-v0" in done.stdout


def test_the_world_works_without_gymnasium():
    done = run_python(
        "import sys; sys.modules['gymnasium'] = None\n"  # makes `import gymnasium` fail
        "import numpy as np, higher_dist\n"
        "from higher_dist.world import BatchedFetchAttr\n"
        "from higher_dist.world.gym_env import FetchAttrEnv\n"
        "from higher_dist.config_presets import small_world\n"
        "assert FetchAttrEnv.__mro__[1] is object\n"
        "env = FetchAttrEnv(small_world()); obs, _ = env.reset(seed=1); env.step(2)\n"
        "b = BatchedFetchAttr(small_world(), 2); b.reset(); b.step(np.array([0, 1]))\n"
        "print('ok')\n")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok"
