"""The generator on a level whose missions name a location seen from the start (BabyAI-OpenDoorLoc-v0): it is
told where the object in front lay (`where`, a location mask reckoned from the episode) and learns to name a
location from it, which one view cannot show; the dataset keeps that mask with each pair and in checkpoints."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from higher_dist.config import GeneratorConfig
from higher_dist.config_presets import make_config
from higher_dist.learning.episode import SUCCESS, Episode
from higher_dist.learning.hindsight.generator import GeneratorTrainer, InstructionGenerator
from higher_dist.learning.hindsight.generator_data import GeneratorDataset
from higher_dist.world.spec import BABYAI_DOOR, WorldSpec

torch.set_num_threads(1)

SMALL = GeneratorConfig(embed_dim=8, conv_channels=(16, 16), word_embed_dim=16, hidden=64, lr=3e-3,
                        batch_size=64, capacity=4000, n_min=100, min_accuracy=0.8)
SPEC = WorldSpec.of(make_config("higher", "BabyAI-OpenDoorLoc-v0").world)
PAPER_SPEC = WorldSpec.of(make_config("higher", "paper").world)
GOTO_SPEC = WorldSpec.of(make_config("higher", "BabyAI-GoToLocal-v0").world)


def door_pairs(n: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Views with a closed door of a random colour in front, masks with one left/right bit and one front/behind
    bit, and the level's kind of mission naming one of the two at random: "open the door on your left"."""
    views = np.zeros((n, *SPEC.view_shape), np.uint8)
    views[..., 0] = 1  # empty
    r, c = SPEC.view_size - 2, SPEC.view_size // 2
    views[:, r, c, 0], views[:, r, c, 1], views[:, r, c, 2] = BABYAI_DOOR, rng.integers(0, 6, n), 1
    side, depth = rng.integers(0, 2, n), 2 + rng.integers(0, 2, n)  # bits 0/1 and 2/3
    where = (1 << side) | (1 << depth)
    loc = np.where(rng.random(n) < 0.5, side, depth)
    attrs = np.stack([np.full(n, -1), np.full(n, 3), loc, np.zeros(n, int)], axis=1)
    return views, SPEC.language.mission_tokens(attrs), where


def test_only_levels_that_name_locations_get_the_input():
    assert SPEC.has_locations and not GOTO_SPEC.has_locations and not PAPER_SPEC.has_locations
    assert InstructionGenerator(SMALL, SPEC).where is not None
    assert InstructionGenerator(SMALL, GOTO_SPEC).where is None and InstructionGenerator(SMALL, PAPER_SPEC).where is None
    # Where no location is ever named, the reckoning is not even run: zeros.
    frames, actions = np.zeros((4, 7, 7, 4), np.uint8), np.array([2, 1, 2])
    assert GOTO_SPEC.start_locations(frames, actions, [1, 3]).tolist() == [0, 0]


def test_the_generator_names_a_true_location_from_where_and_cannot_without_it():
    rng = np.random.default_rng(0)
    trainer = GeneratorTrainer(SMALL, SPEC, seed=0)
    trainer.dataset.add_many(*door_pairs(3000, rng))
    for _ in range(4):
        trainer.train_steps(100)
    views, missions, where = door_pairs(500, np.random.default_rng(1))
    told = trainer.evaluate_pairs(views, missions, where)
    assert told["exact"] >= 0.95, told
    # The truth holds every location of the mask: a generator that names the other true location is right.
    truth = SPEC.fulfilled_by(views, missions, where)
    assert (truth[:, 2] == where).all()
    # The same views without the mask: the location is a guess (about half right, with two of four true).
    blind = trainer.evaluate_pairs(views, missions, np.zeros(500, np.int64))
    assert blind["exact"] < 0.8, blind


def test_the_dataset_keeps_the_reckoned_mask_and_checkpoints_it():
    length = 4
    frames = np.zeros((length + 1, *SPEC.view_shape), np.uint8)
    frames[..., 0] = 1
    # right, forward, forward, toggle: the cell faced before the toggle (frame 3) is three cells to the right of
    # the start, on its row: "on your right" (bit 1) only.
    actions = np.array([1, 2, 2, 5], np.uint8)
    mission = SPEC.language.mission_tokens(np.array([[-1, 3, 1, 0]]))[0]  # "open the door on your right"
    ep = Episode(frames=frames, actions=actions, rewards=np.array([0, 0, 0, 0.9], np.float32), mission=mission,
                 outcome=SUCCESS, picked=np.array([1, 3, 2, 0], np.int8), goal=np.array([-1, 3, 1, 0], np.int8))
    dataset = GeneratorDataset(10, 0.5, seed=0, spec=SPEC)
    assert dataset.add_episode(ep)
    assert dataset.where[0] == SPEC.start_locations(frames, actions, [length - 1])[0] == 2
    dataset.add_many(*door_pairs(5, np.random.default_rng(2)))
    restored = GeneratorDataset(10, 0.5, seed=0, spec=SPEC)
    restored.load_state_dict(dataset.state_dict())
    np.testing.assert_array_equal(restored.where, dataset.where)
    # A dataset state without masks (a world whose missions never name a location) loads as zeros.
    state = dataset.state_dict()
    del state["where"]
    restored.load_state_dict(state)
    assert (restored.where == 0).all()


def test_a_trainer_on_such_a_level_resumes_identically():
    rng = np.random.default_rng(3)
    cfg = replace(SMALL, capacity=500)
    a = GeneratorTrainer(cfg, SPEC, seed=4)
    a.dataset.add_many(*door_pairs(400, rng))
    a.train_steps(5)
    b = GeneratorTrainer(cfg, SPEC, seed=9)
    b.load_state_dict(a.state_dict())
    assert a.train_steps(5) == b.train_steps(5)
    views, _, where = door_pairs(40, np.random.default_rng(5))
    np.testing.assert_array_equal(a.generate(views, where), b.generate(views, where))
