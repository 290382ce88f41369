"""Learning, shown by runs: the single-process runner (the same components as the cluster) learns the
small world well above chance, and with the `higher` preset it relabels with its learned generator."""
import numpy as np
import pytest
import torch

from higher_dist.config_presets import make_config
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.episode import SUCCESS
from higher_dist.learning.runner import SingleProcessRunner

pytestmark = pytest.mark.slow


def random_success_rate(cfg, episodes=400, seed=123) -> float:
    collector = EpisodeCollector(cfg.world, 32, cfg.network.frame_stack, seed=seed)
    rng = np.random.default_rng(seed)
    results = []
    while len(results) < episodes:
        for ep in collector.step(rng.integers(0, 4, size=collector.n_envs)):
            results.append(ep.outcome == SUCCESS)
    return float(np.mean(results))


def run(preset: str, frames: int, **overrides):
    torch.set_num_threads(1)
    cfg = make_config(preset, "small", actors=1, frames=frames, **overrides)
    records = []
    runner = SingleProcessRunner(cfg, log=records.append)
    runner.run(metrics_every=frames // 4)
    return cfg, runner, records


def test_her_learns_the_small_world_well_above_chance():
    cfg, runner, records = run("her", 12_000, **{"eval.every_frames": 12_000, "eval.episodes": 64})
    chance = random_success_rate(cfg)
    final = records[-1]
    assert final["frames"] >= 12_000
    assert final["relabelled_episodes"] > 0  # the expert relabelled wrong picks
    assert final["relabel_accuracy"] == 1.0  # the expert describes what was picked
    # Greedy success on training goals, measured apart from exploration.
    assert final["success_rate_eval_train"] >= chance + 0.3, (final, chance)
    # The training success rate rose over the run.
    assert records[-1]["success_rate_train"] > records[0]["success_rate_train"]


def test_higher_relabels_with_its_learned_generator():
    cfg, runner, records = run("higher", 12_000, **{"generator.n_min": 60, "eval.every_frames": 10**9})
    final = records[-1]
    m = runner.relabeler.metrics()
    assert m["relabel_strategy"] == "learned"
    assert m["relabel_dataset_size"] >= 60 and m["relabel_gate_open"]
    assert m["generator_val_accuracy"] is not None and m["generator_val_accuracy"] >= 0.5
    assert final["relabelled_episodes"] > 0
    assert m["relabel_accuracy"] is not None and m["relabel_accuracy"] >= 0.5


def test_a_trained_generator_trains_at_the_trained_pace():
    # The small world's generator passes 0.5 exact match within the run: from then on its frames earn
    # the trained pace (5 per 1000 frames) instead of the small world's 50.
    cfg, runner, _ = run("higher", 12_000, **{"generator.n_min": 60, "eval.every_frames": 10**9,
                                               "generator.trained_accuracy": 0.5,
                                               "generator.trained_updates_per_kframe": 5.0})
    pace, trainer = runner.pace, runner.relabeler.trainer
    assert trainer.val_accuracy >= 0.5 and 0 < pace.frames_trained < pace.frames
    full = cfg.generator.updates_per_kframe
    earned = int((pace.frames - pace.frames_trained) * full / 1000 + pace.frames_trained * 5.0 / 1000)
    assert pace.settled == earned < int(pace.frames * full / 1000)
    assert trainer.steps <= pace.settled


def test_the_recurrent_core_learns_the_small_world_well_above_chance():
    cfg, runner, records = run("her", 12_000, **{"network.core": "gru", "eval.every_frames": 12_000,
                                                 "eval.episodes": 64})
    assert cfg.network.frame_stack == 1 and runner.core.recurrent
    chance = random_success_rate(cfg)
    final = records[-1]
    assert final["success_rate_eval_train"] >= chance + 0.3, (final, chance)
    assert records[-1]["success_rate_train"] > records[0]["success_rate_train"]
