"""The paper's methods (presets), the two worlds and the two profiles, as functions that make a Config.

`make_config(preset, world, profile, **overrides)` is the one way a run's config is made: the dataclass
defaults of config.py, then the world's and the preset's settings, then the profile, then `--set`
overrides by dotted name. docs/decisions.md says why each setting here was chosen.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

from higher_dist.config import (PRESETS, PROFILES, WORLDS, Config, ConfigError, EvalConfig, GeneratorConfig,
                                RelabelConfig, WorldConfig, from_dict, is_babyai_world, override)


def small_world() -> WorldConfig:
    """A world small enough to learn in CPU minutes: tests and smoke runs."""
    return WorldConfig(
        name="small", room_size=5, n_objects=2, colors=("red", "green"), types=("key", "ball"),
        shades=("neutral",), sizes=("medium",), max_steps=20, heldout_count=2,
    )


def world_by_name(name: str) -> WorldConfig:
    if name == "paper":
        return WorldConfig()
    if name == "small":
        return small_world()
    if is_babyai_world(name):
        # The level's view and step limit come from minigrid when the world is built (max_steps 0).
        return WorldConfig(name=name, max_steps=0, heldout_count=0)
    raise ConfigError(f"world: unknown world {name!r}; choose one of {', '.join(WORLDS)} "
                      f"or a BabyAI pickup, go-to or open level such as BabyAI-PickupDist-v0")


# What each of the paper's methods relabels its failed episodes with.
PRESET_RELABEL = {
    "dqn": RelabelConfig("none"), "reward": RelabelConfig("none"), "her": RelabelConfig("expert"),
    "noisy-her": RelabelConfig("noisy", 0.2), "higher": RelabelConfig("learned"),
}


# The Ape-X ladder's spread on the small world (tests, smoke runs), where episodes are short and most
# slots should still explore; the paper world and BabyAI levels take the default's wider one
# (docs/decisions.md, "Ape-X exploration, a wide ladder").
NARROW_LADDER = 2.0

# The paper world's missions name attribute values in any order after a prefix that names nothing, so
# its instruction encoder is a bag of words; BabyAI levels, the small world (tests, smoke runs) and the
# paper's profile keep the GRU (docs/decisions.md, "A bag of words on the paper world").
PAPER_WORLD_TEXT = "bow"

# Returns over 3 steps on the small world, whose episodes last at most 20 steps; the paper world and
# BabyAI levels take the default's 5 (docs/decisions.md, "5-step returns").
SHORT_N_STEP = 3


def make_config(preset: str = "higher", world: str = "paper", profile: str = "default",
                **overrides: Any) -> Config:
    """The config of one of the paper's methods on a named world under a profile; any field may then
    be overridden by dotted name."""
    if preset not in PRESETS:
        raise ConfigError(f"preset: unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if profile not in PROFILES:
        raise ConfigError(f"profile: unknown profile {profile!r}; choose one of {', '.join(PROFILES)}")
    w = world_by_name(world)
    relabel = PRESET_RELABEL[preset]
    if preset == "reward":
        w = replace(w, reward_shaping=True)
    cfg = Config(preset=preset, world=w, relabel=relabel)
    if world == "small":
        # Few goals, runs of seconds to minutes (tests, smoke runs): small batches and buffers, no compile.
        cfg = replace(
            cfg,
            dqn=replace(cfg.dqn, batch_size=64, lr=5e-4, target_period=500, n_step=SHORT_N_STEP, compile=False),
            generator=replace(cfg.generator, n_min=100, capacity=2000, updates_per_kframe=50.0, eval_every_updates=50),
            replay=replace(cfg.replay, capacity=50_000, min_size=500, beta_frames=200_000, samples_per_insert=8.0),
            exploration=replace(cfg.exploration, decay_frames=50_000, apex_alpha=NARROW_LADDER),
            eval=EvalConfig(every_frames=10_000, episodes=32),
            frames=200_000, envs_per_actor=16,
        )
    else:
        cfg = PAPER_WORLD_TUNING.get(preset, lambda c: c)(cfg)
    if world == "paper":
        cfg = replace(cfg, network=replace(cfg.network, text=PAPER_WORLD_TEXT),
                      generator=replace(cfg.generator, **PAPER_WORLD_GENERATOR),
                      relabel=replace(cfg.relabel, **PAPER_WORLD_RELABEL.get(preset, {})))
    if is_babyai_world(world):
        cfg = _on_a_babyai_level(cfg)
    if profile == "paper":
        cfg = paper_profile(cfg)
    if overrides.get("network.core") == "gru":
        # The recurrent core reads one view per step: no frame stack, unless a flag asks for one (refused).
        overrides = {"network.frame_stack": 1, **overrides}
    cfg = override(cfg, **overrides)
    cfg = from_dict(cfg.to_dict())  # types first: --set dqn.lr=fast is refused, not a TypeError
    return cfg


# The generator on the paper world: learns its grammar from the first hundred pairs when it trains at a
# higher rate with a narrower view encoder (docs/decisions.md, "A generator that learns from few pairs").
PAPER_WORLD_GENERATOR = {"lr": 3e-3, "conv_channels": (16, 32)}


def _higher_on_the_paper_world(cfg: Config) -> Config:
    # The gate opens on the pairs the shared exploration brings (docs/decisions.md, "HIGhER's gate").
    return replace(cfg, generator=replace(cfg.generator, n_min=100))


def _on_a_babyai_level(cfg: Config) -> Config:
    # A BabyAI level's missions are short and its random successes frequent (PickupDist: ~4 pairs per
    # 1000 frames): the generator may start from smaller batches and a smaller dataset, trained faster
    # and checked more often on a larger validation share (docs/decisions.md, "BabyAI levels"). A
    # 1M-frame budget fits a CPU machine.
    return replace(cfg, frames=1_000_000,
                   generator=replace(cfg.generator, n_min=50, batch_size=32, eval_every_updates=50,
                                     updates_per_kframe=40.0, val_fraction=0.2))


# HIGhER on the paper world keeps the failures it would relabel out of the replay until its gate opens,
# so that its agent does not learn, while it waits, that every pick fails (docs/decisions.md, "Failures
# kept out of the replay while the gate is shut").
PAPER_WORLD_RELABEL = {"higher": {"withheld_while_gated": True}}


# Per-preset settings measured on the paper world, applied on top of the dataclass defaults.
PAPER_WORLD_TUNING = {"higher": _higher_on_the_paper_world}
PAPER_DECAY_FRAMES = {"higher": 400_000}  # the paper's linear epsilon span; 100_000 for the others


def paper_profile(cfg: Config) -> Config:
    """The paper's settings on top of a preset (docs/paper_settings.md): the generator without the
    front-cell shortcut, used ungated from 1000 pairs with every failure stored while it waits, epsilon
    linear from 1.0 to 0.05 over 1e5 frames (4e5 for HIGhER), and the instruction read by a GRU. Its
    replay ratio and terminal time-outs stay options."""
    return replace(
        cfg, profile="paper", network=replace(cfg.network, text="gru"),
        relabel=replace(cfg.relabel, withheld_while_gated=False),
        generator=replace(cfg.generator, front_cell_shortcut=False, n_min=1000, min_accuracy=0.0,
                          lr=GeneratorConfig.lr, conv_channels=GeneratorConfig.conv_channels),
        exploration=replace(cfg.exploration, kind="linear", eps_start=1.0, eps_end=0.05,
                            decay_frames=PAPER_DECAY_FRAMES.get(cfg.preset, 100_000)),
    )
