"""One typed, frozen config tree for every role, with presets for the paper's five methods.

The learner owns the config of a run: actors and the relabeler receive it in the welcome message as a
plain dict (`to_dict`) and rebuild it with `from_dict`, so no role can run with a config that differs
from the learner's. `validate` refuses inconsistent values with a message that names the field.
"""
from __future__ import annotations

import dataclasses
import json
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Any

COLORS = ("red", "green", "blue", "purple", "yellow", "grey")
TYPES = ("key", "ball")
SHADES = ("very_light", "light", "neutral", "dark", "very_dark")
SIZES = ("tiny", "small", "medium", "large", "giant")

PRESETS = ("dqn", "her", "noisy-her", "higher", "reward")
WORLDS = ("paper", "small")
RATIO_COUNTS = ("env_frames", "transitions")
# Profiles apply a whole set of choices on top of a preset and a world (before --set overrides):
# "default" is ours (docs/decisions.md), "paper" the paper's (docs/paper_settings.md lists every
# difference, and the paper's settings that stay options).
PROFILES = ("default", "paper")  # what the samples-per-insert limiter counts as inserts


class ConfigError(ValueError):
    """A config value that cannot work; the message names the field and the reason."""


@dataclass(frozen=True)
class WorldConfig:
    name: str = "paper"
    room_size: int = 10  # interior cells per side; the outer wall is added around it
    n_objects: int = 10
    colors: tuple[str, ...] = COLORS
    types: tuple[str, ...] = TYPES
    shades: tuple[str, ...] = SHADES
    sizes: tuple[str, ...] = SIZES
    max_steps: int = 40
    view_size: int = 7
    heldout_count: int = 60  # objects kept out of training goals (paper: 60 of 300)
    split_seed: int = 0
    reward_shaping: bool = False  # DQN+reward: 0.25 per matching attribute of the picked object


@dataclass(frozen=True)
class NetworkConfig:
    # Lean on purpose: the learner must do thousands of samples/s on one CPU thread. A supervised probe
    # (where is the described object?) scored these sizes within noise of twice-as-wide ones, and FiLM
    # above concatenation (docs/decisions.md).
    embed_dim: int = 8  # per-channel value embedding of the 7x7x4 view
    conv_channels: tuple[int, ...] = (16, 32)
    frame_stack: int = 4  # memory of the past for partial observability; 1 = none (8: decisions.md round 3)
    fusion: str = "film"  # film | concat
    word_embed_dim: int = 16
    text_hidden: int = 32  # GRU over the instruction
    hidden: int = 64
    dueling: bool = True
    # The head's output layers start scaled by this (biases at zero), so every seed starts with Q ~ 0.
    # With PyTorch's default init (1.0) the initial Q of a seed ranged from -0.25 to +0.7 on the paper
    # world; with a target copied every 48k frames that offset decays by only gamma^n per copy, and a
    # seed starting at +0.6 valued wandering above picking and stalled (docs/decisions.md, round 3).
    head_init_scale: float = 0.01


@dataclass(frozen=True)
class DQNConfig:
    # Tuned on the paper world (docs/decisions.md, "Tuning on the paper world"); the small world keeps
    # the batch 64 / 5e-4 it was tuned with (make_config).
    batch_size: int = 256
    lr: float = 5e-4
    # > 0: the learning rate falls linearly from lr to lr * lr_end_fraction over this many env frames
    # (the learner's frame count, the run's one clock, whatever the run's budget), then stays there.
    # 0: constant lr, the default. A decay over 2M frames lifted HER's greedy success over 1.5M-2M by
    # 8-17 points but not HIGhER's, which learns later and ended about 20 points behind HER: it favours
    # the faster method and so confounds the comparison between methods (docs/decisions.md, round 4).
    lr_decay_frames: int = 0
    lr_end_fraction: float = 0.1
    adam_eps: float = 1e-6
    gamma: float = 0.99
    n_step: int = 3
    huber_delta: float = 1.0
    grad_clip: float = 10.0
    target_update: str = "period"  # period | polyak
    # Updates between hard target copies: 1500 at batch 256 and 8 samples per frame is a copy every
    # 48k env frames. Copies every 5k-16k frames learned half as much per frame on the paper world.
    target_period: int = 1500
    polyak_tau: float = 0.005
    double: bool = True
    # > 0: the learner also keeps an exponential moving average of the online weights
    # (avg <- avg + tau * (online - avg) after every update; 1 / tau updates is its memory: 1000 updates,
    # 32k env frames here) and every greedy evaluation scores it beside the online weights, on the same
    # goals (`*_averaged` metrics). The actors act with the online weights and the loss never reads the
    # average. On the paper world it read above the online weights in 8 runs of 2M frames from 500k on
    # (HER: by 4-13 points from 1M) and swung half as much between evaluations (docs/decisions.md,
    # round 4). 0: no average.
    average_tau: float = 0.001
    # Speed levers, each measured with `higher-bench learner --levers` (docs/benchmarks.md); none
    # changes the maths. compile: torch.compile the loss (forward + backward), built on a background
    # thread while eager updates run, eager for good if it fails. joint_online: one online forward over
    # obs and next_obs stacked. prefetch: sample the next batch on a thread during the update.
    compile: bool = True
    joint_online: bool = False
    prefetch: bool = False


@dataclass(frozen=True)
class ReplayConfig:
    capacity: int = 200_000  # transitions (frames), FIFO eviction by whole episodes
    alpha: float = 0.6
    beta_start: float = 0.4
    beta_end: float = 1.0
    beta_frames: int = 5_000_000  # frames over which beta anneals to beta_end
    min_size: int = 2_000  # transitions before learning starts
    samples_per_insert: float = 8.0  # replay ratio kept by the rate limiter (as in Reverb)
    # What one "insert" of that ratio is. "env_frames": frames of original episodes only, so every
    # method gets the same updates per env frame (the comparison between methods uses this);
    # "transitions": every stored transition, relabelled copies included (HER and HIGhER then get up
    # to ~1.4x the updates of DQN per env frame).
    ratio_counts: str = "env_frames"
    # False: a time-out is a truncation and bootstraps from its last frame (correct for a time limit
    # the agent cannot see). True: stored as terminal, as the paper's code did.
    timeouts_terminal: bool = False
    priority_eps: float = 1e-3
    checkpoint_replay: bool = False


@dataclass(frozen=True)
class ExplorationConfig:
    kind: str = "apex"  # apex | linear
    eps_base: float = 0.4  # Ape-X: eps_i = eps_base ** (1 + apex_alpha * i / (N - 1))
    apex_alpha: float = 2.0  # small alpha suits a handful of actors
    eps_start: float = 1.0  # linear decay (the paper's schedule)
    eps_end: float = 0.05
    decay_frames: int = 1_000_000
    # apex only: every slot starts at epsilon 1.0 and decays linearly to its rung of the ladder over
    # this many env frames (0: the ladder from the start). Early random picks feed HER its wrong picks
    # and HIGhER's generator its first successes, while the greedy rungs take over later.
    warmup_frames: int = 0
    # Temporally extended exploration, ez-greedy (Dabney et al. 2021): an exploratory action is held
    # for n steps, n ~ zeta(repeat_mu) capped at repeat_max, so a random walk can cross the room instead
    # of jittering in place. repeat_max = 1 is plain epsilon-greedy.
    repeat_max: int = 1
    repeat_mu: float = 2.0


@dataclass(frozen=True)
class GeneratorConfig:
    embed_dim: int = 16
    conv_channels: tuple[int, ...] = (32, 64)
    word_embed_dim: int = 32
    hidden: int = 128
    max_len: int = 12  # decoding cap, END included
    lr: float = 1e-3
    batch_size: int = 64
    capacity: int = 20_000  # (observation, instruction) pairs kept, FIFO
    val_fraction: float = 0.1
    n_min: int = 1000  # gate: pairs needed before relabelling (paper: 1000)
    # The summed embedding of the cell in front (where a picked object lies) fed straight to the
    # decoder: ~99% exact match at 5000 pairs, against ~70% for the paper's generator, which has none.
    front_cell_shortcut: bool = True
    min_accuracy: float = 0.5  # gate: validation exact match needed; 0 = the paper's ungated variant
    # Training pace, as data: generator updates per 1000 env frames of original episodes. The runner and
    # the relabeler service both enforce it (learning/agent.GeneratorPace), so the generator's training
    # per frame does not depend on the machine.
    # 10/kframe: ~10 updates/s at 1,000 frames/s, a fraction of a core (one update of batch 64 costs
    # 15-40 ms here), and 5,000 updates by 500k frames, where 1,500 reach 99% exact match on 5,000 pairs.
    updates_per_kframe: float = 10.0
    eval_every_updates: int = 200  # validation exact match (the gate's input) every this many updates


@dataclass(frozen=True)
class RelabelConfig:
    strategy: str = "none"  # none | expert | noisy | learned
    noise_p: float = 0.2  # noisy expert: each attribute swapped to another value with this probability


@dataclass(frozen=True)
class EvalConfig:
    every_frames: int = 50_000
    # Per goal set (training and held-out) each time, one per environment (unbiased): 256 puts the
    # standard error at 3 points or less.
    episodes: int = 256


@dataclass(frozen=True)
class Config:
    preset: str = "higher"
    profile: str = "default"  # see PROFILES
    world: WorldConfig = field(default_factory=WorldConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    dqn: DQNConfig = field(default_factory=DQNConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    generator: GeneratorConfig = field(default_factory=GeneratorConfig)
    relabel: RelabelConfig = field(default_factory=RelabelConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    actors: int = 2
    envs_per_actor: int = 32
    frames: int = 5_000_000  # env frames budget of the run
    seed: int = 0
    device: str = "cpu"
    torch_threads: int = 1
    weights_every: int = 20  # learner updates between weight publications
    stats_every_s: float = 2.0
    checkpoint_every_s: float = 120.0
    tensorboard: bool = False  # also write metrics as TensorBoard event files (needs the tensorboard extra)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)


def override(cfg: Config, **overrides: Any) -> Config:
    """Replace fields by dotted name: override(cfg, **{"dqn.lr": 1e-3, "frames": 10})."""
    for key, value in overrides.items():
        cfg = _set_path(cfg, key.split("."), value, key)
    return cfg


def _set_path(obj: Any, path: list[str], value: Any, full: str) -> Any:
    names = {f.name for f in fields(obj)}
    if path[0] not in names:
        raise ConfigError(f"{full}: no such config field (known here: {', '.join(sorted(names))})")
    if len(path) == 1:
        return replace(obj, **{path[0]: value})
    return replace(obj, **{path[0]: _set_path(getattr(obj, path[0]), path[1:], value, full)})


def from_dict(data: dict[str, Any]) -> Config:
    """Rebuild a Config from `to_dict` output (e.g. received in a welcome message), then validate."""
    if not isinstance(data, dict):
        raise ConfigError("config: expected a mapping")
    cfg = _build(Config, data, "")
    validate(cfg)
    return cfg


def _build(cls: Any, data: dict[str, Any], prefix: str) -> Any:
    known = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ConfigError(f"{prefix or 'config'}: unknown fields {sorted(unknown)}")
    kwargs: dict[str, Any] = {}
    defaults = cls()
    for name, value in data.items():
        default = getattr(defaults, name)
        where = f"{prefix}{name}"
        if dataclasses.is_dataclass(default):
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: expected a mapping")
            kwargs[name] = _build(type(default), value, where + ".")
        elif isinstance(default, tuple):
            if not isinstance(value, (list, tuple)):
                raise ConfigError(f"{where}: expected a list")
            kwargs[name] = tuple(value)
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{where}: expected true or false, got {value!r}")
            kwargs[name] = value
        elif isinstance(default, (int, float)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{where}: expected a number, got {value!r}")
            if isinstance(default, int) and not isinstance(default, bool) and float(value) != int(value):
                raise ConfigError(f"{where}: expected an integer, got {value!r}")
            kwargs[name] = type(default)(value)
        else:
            if not isinstance(value, str):
                raise ConfigError(f"{where}: expected a string, got {value!r}")
            kwargs[name] = value
    return cls(**kwargs)


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


def validate_world(w: WorldConfig) -> None:
    """Refuse a world that cannot be built, naming the field. Also called by the world itself, which
    is built on its own by tests, benchmarks and the Gymnasium view."""
    if not isinstance(w, WorldConfig):
        raise ConfigError(f"world: expected a WorldConfig, got {type(w).__name__}")
    for name in ("room_size", "n_objects", "max_steps", "view_size", "heldout_count", "split_seed"):
        value = getattr(w, name)
        _check(isinstance(value, numbers.Integral) and not isinstance(value, bool),
               f"world.{name}: expected an integer, got {value!r}")
    _check(w.room_size >= 2, f"world.room_size: must be >= 2, got {w.room_size}")
    _check(w.n_objects >= 1, f"world.n_objects: must be >= 1, got {w.n_objects}")
    # One cell is the agent's, the others may hold objects.
    _check(w.n_objects < w.room_size ** 2,
           f"world.n_objects: {w.n_objects} objects do not fit with the agent in a "
           f"{w.room_size}x{w.room_size} room ({w.room_size ** 2 - 1} free cells)")
    _check(w.max_steps >= 1, f"world.max_steps: must be >= 1, got {w.max_steps}")
    _check(3 <= w.view_size <= 15 and w.view_size % 2 == 1,
           f"world.view_size: must be odd and in [3, 15], got {w.view_size}")
    for name, values, full in (("colors", w.colors, COLORS), ("types", w.types, TYPES),
                               ("shades", w.shades, SHADES), ("sizes", w.sizes, SIZES)):
        _check(len(values) >= 1, f"world.{name}: needs at least one value")
        _check(len(set(values)) == len(values), f"world.{name}: repeated values {list(values)}")
        bad = [v for v in values if v not in full]
        _check(not bad, f"world.{name}: unknown values {bad}; allowed: {', '.join(full)}")
    n_kinds = len(w.colors) * len(w.types) * len(w.shades) * len(w.sizes)
    _check(0 <= w.heldout_count < n_kinds,
           f"world.heldout_count: must be in [0, {n_kinds}) for {n_kinds} distinct objects, got {w.heldout_count}")


def validate(cfg: Config) -> None:
    """Refuse a config that cannot work, naming the field."""
    _check(cfg.preset in PRESETS, f"preset: unknown preset {cfg.preset!r}; choose one of {', '.join(PRESETS)}")
    _check(cfg.profile in PROFILES, f"profile: unknown profile {cfg.profile!r}; choose one of {', '.join(PROFILES)}")
    validate_world(cfg.world)
    w = cfg.world
    n = cfg.network
    _check(n.fusion in ("film", "concat"), f"network.fusion: must be film or concat, got {n.fusion!r}")
    _check(n.frame_stack >= 1, f"network.frame_stack: must be >= 1, got {n.frame_stack}")
    _check(n.head_init_scale > 0, f"network.head_init_scale: must be > 0, got {n.head_init_scale}")
    _check(len(n.conv_channels) >= 1, "network.conv_channels: needs at least one layer")
    d = cfg.dqn
    _check(d.batch_size >= 1, f"dqn.batch_size: must be >= 1, got {d.batch_size}")
    _check(d.lr > 0, f"dqn.lr: must be > 0, got {d.lr}")
    _check(d.lr_decay_frames >= 0, f"dqn.lr_decay_frames: must be >= 0 (0: constant lr), got {d.lr_decay_frames}")
    _check(0.0 < d.lr_end_fraction <= 1.0, f"dqn.lr_end_fraction: must be in (0, 1], got {d.lr_end_fraction}")
    _check(0.0 <= d.gamma <= 1.0, f"dqn.gamma: must be in [0, 1], got {d.gamma}")
    _check(d.n_step >= 1, f"dqn.n_step: must be >= 1, got {d.n_step}")
    _check(d.target_update in ("period", "polyak"), f"dqn.target_update: must be period or polyak, got {d.target_update!r}")
    _check(0.0 < d.polyak_tau <= 1.0, f"dqn.polyak_tau: must be in (0, 1], got {d.polyak_tau}")
    _check(0.0 <= d.average_tau <= 1.0, f"dqn.average_tau: must be in [0, 1] (0: no average), got {d.average_tau}")
    r = cfg.replay
    _check(r.capacity >= 2 * (w.max_steps + 1), f"replay.capacity: must hold at least two episodes, got {r.capacity}")
    _check(0 < r.min_size <= r.capacity, f"replay.min_size: must be in (0, capacity={r.capacity}], got {r.min_size}")
    _check(r.alpha >= 0 and 0 <= r.beta_start <= 1 and 0 <= r.beta_end <= 1, "replay: alpha >= 0 and betas in [0, 1]")
    _check(r.samples_per_insert > 0, f"replay.samples_per_insert: must be > 0, got {r.samples_per_insert}")
    _check(r.ratio_counts in RATIO_COUNTS,
           f"replay.ratio_counts: must be {' or '.join(RATIO_COUNTS)}, got {r.ratio_counts!r}")
    e = cfg.exploration
    _check(e.kind in ("apex", "linear"), f"exploration.kind: must be apex or linear, got {e.kind!r}")
    _check(0 <= e.eps_base <= 1 and 0 <= e.eps_end <= e.eps_start <= 1, "exploration: epsilons must lie in [0, 1], end <= start")
    _check(e.warmup_frames >= 0, f"exploration.warmup_frames: must be >= 0, got {e.warmup_frames}")
    _check(e.repeat_max >= 1, f"exploration.repeat_max: must be >= 1, got {e.repeat_max}")
    _check(e.repeat_mu > 0, f"exploration.repeat_mu: must be > 0, got {e.repeat_mu}")
    g = cfg.generator
    _check(0 < g.val_fraction < 1, f"generator.val_fraction: must be in (0, 1), got {g.val_fraction}")
    _check(0 <= g.min_accuracy <= 1, f"generator.min_accuracy: must be in [0, 1], got {g.min_accuracy}")
    _check(g.max_len >= 6, f"generator.max_len: must be >= 6 to hold an instruction, got {g.max_len}")
    _check(g.capacity >= 10, f"generator.capacity: must be >= 10, got {g.capacity}")
    _check(g.updates_per_kframe >= 0, f"generator.updates_per_kframe: must be >= 0, got {g.updates_per_kframe}")
    _check(g.eval_every_updates >= 1, f"generator.eval_every_updates: must be >= 1, got {g.eval_every_updates}")
    rl = cfg.relabel
    _check(rl.strategy in ("none", "expert", "noisy", "learned"),
           f"relabel.strategy: must be none, expert, noisy or learned, got {rl.strategy!r}")
    _check(0 <= rl.noise_p <= 1, f"relabel.noise_p: must be in [0, 1], got {rl.noise_p}")
    _check(cfg.actors >= 1, f"actors: must be >= 1, got {cfg.actors}")
    _check(cfg.envs_per_actor >= 1, f"envs_per_actor: must be >= 1, got {cfg.envs_per_actor}")
    _check(cfg.frames >= 1, f"frames: must be >= 1, got {cfg.frames}")
    _check(cfg.device == "cpu" or cfg.device.startswith("cuda"), f"device: must be cpu or cuda[:N], got {cfg.device!r}")
    _check(cfg.torch_threads >= 1, f"torch_threads: must be >= 1, got {cfg.torch_threads}")
    _check(cfg.weights_every >= 1, f"weights_every: must be >= 1, got {cfg.weights_every}")
