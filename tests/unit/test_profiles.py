"""Profiles: the paper's settings with one switch, recorded in the run's config."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from higher_dist.config_flags import add_config_flags, config_from_args
from higher_dist.learning.hindsight.generator_measure import make_pairs
from higher_dist.config import ConfigError, WorldConfig, from_dict, is_babyai_world
from higher_dist.config_presets import make_config
from higher_dist.learning.agent import AgentBuilder
from higher_dist.learning.hindsight.generator import GeneratorTrainer, InstructionGenerator
from higher_dist.rundir import RunDir


@pytest.mark.parametrize("preset, decay", [("her", 100_000), ("higher", 400_000), ("dqn", 100_000)])
def test_paper_profile_applies_the_papers_settings_on_top_of_a_preset(preset, decay):
    ours, paper = make_config(preset, "paper"), make_config(preset, "paper", "paper")
    assert ours.profile == "default" and paper.profile == "paper"
    # The method stays the preset's; only HIGhER's default of keeping failures out while its gate is shut
    # departs from the paper, and the profile turns it off.
    assert paper.preset == preset and paper.relabel.strategy == ours.relabel.strategy
    assert paper.relabel == replace(ours.relabel, withheld_while_gated=False)
    assert ours.relabel.withheld_while_gated == (preset == "higher") and not paper.relabel.withheld_while_gated
    e = paper.exploration
    assert (e.kind, e.eps_start, e.eps_end, e.decay_frames) == ("linear", 1.0, 0.05, decay)
    g = paper.generator
    assert not g.front_cell_shortcut and g.n_min == 1000 and g.min_accuracy == 0.0
    assert ours.generator.front_cell_shortcut
    # Options of the paper's that the profile leaves off, and overrides still win over the profile.
    assert not paper.replay.timeouts_terminal
    tweaked = make_config(preset, "paper", "paper", **{"generator.n_min": 2000, "replay.timeouts_terminal": True})
    assert tweaked.generator.n_min == 2000 and tweaked.replay.timeouts_terminal and tweaked.profile == "paper"


def test_the_profile_is_recorded_in_config_json_and_travels_with_the_config(tmp_path):
    import argparse
    p = argparse.ArgumentParser()
    add_config_flags(p)
    cfg = config_from_args(p.parse_args(["--preset", "higher", "--profile", "paper", "--frames", "1000"]))
    RunDir(str(tmp_path / "run")).write_config(cfg)
    written = json.loads((tmp_path / "run" / "config.json").read_text())
    assert written["profile"] == "paper" and written["generator"]["front_cell_shortcut"] is False
    assert from_dict(written) == cfg  # an actor rebuilding it from the welcome gets the same settings
    with pytest.raises(SystemExit):
        p.parse_args(["--profile", "fastest"])
    with pytest.raises(ConfigError, match="profile"):
        make_config("her", "paper", "fastest")
    with pytest.raises(ConfigError, match="profile"):
        from_dict({**written, "profile": "fastest"})


def test_generator_without_the_front_cell_shortcut_reads_conv_features_only():
    torch.manual_seed(0)
    cfg = make_config("higher", "paper", "paper").generator
    with_cut = InstructionGenerator(make_config("higher", "paper").generator)
    without = InstructionGenerator(cfg)
    assert without.context.in_features == without.encoder.out_dim
    # The shortcut: one embedding row per channel of the front cell (kind, color, shade, size), side by side.
    assert with_cut.context.in_features == with_cut.encoder.out_dim + 4 * with_cut.cfg.embed_dim
    # It still learns: the loss falls on a few hundred pairs (a check of the path, not of accuracy;
    # a narrow generator keeps it cheap).
    narrow = replace(cfg, embed_dim=4, conv_channels=(8, 8), word_embed_dim=8, hidden=32, lr=3e-3, batch_size=32)
    trainer = GeneratorTrainer(narrow, seed=0)
    views, missions, _ = make_pairs(WorldConfig(), 256, "train", np.random.default_rng(0))
    trainer.dataset.add_many(views, missions)
    first = trainer.train_steps(3)
    assert trainer.train_steps(40) < 0.8 * first


def test_paper_world_tuning_applies_to_the_paper_world_only_and_the_paper_profile_overrides_it():
    higher = make_config("higher", "paper")
    assert higher.generator.n_min < 1000
    assert (higher.dqn.batch_size, make_config("her", "small").dqn.batch_size) == (256, 64)
    paper = make_config("higher", "paper", "paper")
    assert paper.generator.n_min == 1000 and paper.exploration.kind == "linear"


@pytest.mark.parametrize("world", ["paper", "small", "BabyAI-PickupDist-v0"])
def test_every_method_explores_and_learns_alike_on_a_world(world):
    """The paper's comparison is fair only if the methods differ in what they relabel: on each world
    every preset of the default profile gets the same exploration, DQN settings and replay."""
    configs = {p: make_config(p, world) for p in ("dqn", "her", "higher")}
    for part in ("exploration", "dqn", "replay"):
        values = {p: getattr(c, part) for p, c in configs.items()}
        assert len(set(values.values())) == 1, f"{world}: {part} differs between presets: {values}"


@pytest.mark.parametrize("world, spread", [("paper", 7.0), ("small", 2.0), ("BabyAI-PickupDist-v0", 7.0),
                                           ("BabyAI-PickupLoc-v0", 7.0), ("BabyAI-GoToLocal-v0", 7.0)])
def test_the_ladders_spread_is_the_worlds_and_a_flag_still_sets_it(world, spread):
    """The wide Ape-X ladder on the paper world and BabyAI levels, a spread of 2 on the small world, and
    `--set exploration.apex_alpha` overrides either (the world's choice comes before the flags)."""
    for preset in ("dqn", "her", "higher"):
        cfg = make_config(preset, world)
        assert cfg.exploration.kind == "apex" and cfg.exploration.apex_alpha == spread
        assert make_config(preset, world, **{"exploration.apex_alpha": 4.5}).exploration.apex_alpha == 4.5
    # the paper profile's linear epsilon is untouched by the world's ladder
    assert make_config("her", world, "paper").exploration.kind == "linear"


@pytest.mark.parametrize("world, n_step", [("paper", 5), ("small", 3), ("BabyAI-PickupDist-v0", 5),
                                           ("BabyAI-PickupLoc-v0", 5), ("BabyAI-GoToLocal-v0", 5)])
def test_returns_span_five_steps_except_on_the_small_world_and_a_flag_still_sets_them(world, n_step):
    """5-step returns (dqn.n_step's default) for every method on the paper world and BabyAI levels, 3 on the
    small world; `--set dqn.n_step` overrides the world's choice, and the paper profile keeps it (it changes
    exploration and generator). `reward` is not defined on BabyAI levels."""
    presets = ("dqn", "her", "higher") + (() if is_babyai_world(world) else ("reward",))
    for preset in presets:
        assert make_config(preset, world).dqn.n_step == n_step
        assert make_config(preset, world, **{"dqn.n_step": 2}).dqn.n_step == 2
    assert make_config("her", world, "paper").dqn.n_step == n_step


@pytest.mark.parametrize("world, text", [("paper", "bow"), ("small", "gru"), ("BabyAI-PickupDist-v0", "gru"),
                                         ("BabyAI-PickupLoc-v0", "gru")])
def test_the_instruction_encoder_is_the_worlds_and_a_flag_still_sets_it(world, text):
    """A bag of words on the paper world (its word order carries nothing) for every method, the GRU on
    BabyAI levels and the small world; the paper profile reads with the paper's GRU; `--set network.text`
    overrides either."""
    for preset in ("dqn", "her", "higher"):
        assert make_config(preset, world).network.text == text
        other = "gru" if text == "bow" else "bow"
        assert make_config(preset, world, **{"network.text": other}).network.text == other
    assert make_config("her", world, "paper").network.text == "gru"


@pytest.mark.parametrize("world, lr, convs", [("paper", 3e-3, (16, 32)), ("small", 1e-3, (32, 64)),
                                              ("BabyAI-PickupDist-v0", 1e-3, (32, 64))])
def test_the_generator_trains_as_its_world_chose_and_flags_and_the_paper_profile_still_set_it(world, lr, convs):
    """The paper world's generator trains at 3e-3 through (16, 32) convolutions (it learns its grammar from
    the first hundred pairs); other worlds keep the dataclass defaults; every world trains it at one pace
    per frame; `--set` overrides the world's choice, and the paper profile restores the defaults it was
    measured with."""
    cfg = make_config("higher", world)
    assert (cfg.generator.lr, tuple(cfg.generator.conv_channels)) == (lr, convs)
    pace = AgentBuilder(cfg).generator_pace()
    assert (pace.trained_accuracy, pace.updates_per_kframe) == (0.0, cfg.generator.updates_per_kframe)
    assert make_config("higher", world, "paper").generator.trained_accuracy == 0.0
    flagged = make_config("higher", world, **{"generator.lr": 5e-4, "generator.conv_channels": [8, 8]})
    assert (flagged.generator.lr, tuple(flagged.generator.conv_channels)) == (5e-4, (8, 8))
    paper = make_config("higher", world, "paper")
    assert (paper.generator.lr, tuple(paper.generator.conv_channels)) == (1e-3, (32, 64))
    if world == "paper":  # the generator built from the world's config trains as it names
        trainer = GeneratorTrainer(cfg.generator, seed=0)
        widths = [m.out_channels for m in trainer.model.encoder.modules() if isinstance(m, torch.nn.Conv2d)]
        assert widths == list(convs) and trainer.optimizer.param_groups[0]["lr"] == lr
