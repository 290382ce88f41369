"""Equal update budgets: every method gets the same DQN updates per env frame, whatever it relabels."""
import numpy as np
import pytest
import torch

from higher_dist.config import ConfigError
from higher_dist.config_presets import make_config
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.learner import Learner
from higher_dist.learning.hindsight.relabel import make_relabel_strategy


def feed(preset, episodes, **overrides):
    """Feed the same original episodes to a learner of `preset` (with its relabelled copies) and let it
    train as far as the ratio allows; returns (updates, env frames, relabelled copies)."""
    torch.set_num_threads(1)
    cfg = make_config(preset, "small", **{"replay.min_size": 200, "dqn.batch_size": 32, **overrides})
    core = Learner(cfg)
    relabeler = make_relabel_strategy(cfg, seed=0)
    for i in range(0, len(episodes), 16):
        batch = episodes[i:i + 16]
        core.add_episodes(batch + relabeler.relabel(batch))
        core.train_available(max_updates=10_000)
    return core.updates, core.frames, core.relabelled_episodes


@pytest.fixture(scope="module")
def episodes():
    cfg = make_config("dqn", "small").world
    collector = EpisodeCollector(cfg, 16, 4, seed=5)
    rng = np.random.default_rng(5)
    out = []
    while len(out) < 200:
        out += collector.step(rng.choice(4, size=16, p=[0.2, 0.2, 0.3, 0.3]))  # picks often
    return out


def test_relabelled_copies_do_not_buy_extra_updates(episodes):
    dqn_updates, dqn_frames, _ = feed("dqn", episodes)
    her_updates, her_frames, copies = feed("her", episodes)
    assert copies > 10 and dqn_frames == her_frames
    assert dqn_updates > 20
    assert abs(her_updates - dqn_updates) <= 1, (her_updates, dqn_updates)


def test_counting_every_transition_is_a_named_option_that_gives_her_more_updates(episodes):
    dqn_updates, _, _ = feed("dqn", episodes, **{"replay.ratio_counts": "transitions"})
    her_updates, _, copies = feed("her", episodes, **{"replay.ratio_counts": "transitions"})
    assert copies > 10 and her_updates >= dqn_updates + 10, (her_updates, dqn_updates)


def test_an_unknown_ratio_count_is_refused_by_name():
    with pytest.raises(ConfigError, match="replay.ratio_counts"):
        make_config("her", "small", **{"replay.ratio_counts": "episodes"})
