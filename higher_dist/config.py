"""One typed, frozen config tree for every role, with presets for the paper's five methods.

The learner owns the config of a run: actors and the relabeler receive it in the welcome message as a
plain dict (`to_dict`) and rebuild it with `from_dict`, so no role can run with a config that differs
from the learner's. `validate` refuses inconsistent values with a message that names the field.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Any

COLORS = ("red", "green", "blue", "purple", "yellow", "grey")
TYPES = ("key", "ball")
SHADES = ("very_light", "light", "neutral", "dark", "very_dark")
SIZES = ("tiny", "small", "medium", "large", "giant")

PRESETS = ("dqn", "her", "noisy-her", "higher", "reward")  # the paper's methods (config_presets.py)
WORLDS = ("paper", "small")  # our own worlds; a BabyAI level is named by its gymnasium id
# Distinct achieved outcomes one episode records at most (world/spec.py: the first and MAX_LATER more).
MAX_OUTCOMES = 8
MAX_HELD_WHILE_GATED = 100_000  # relabel.held_while_gated: about 1 GB of views on the paper world
MAX_AGREEMENT_DRAWS = 64  # generator.agreement_draws and beam_width: each is one more decoding of a relabel batch
BABYAI_PREFIX = "BabyAI-"


def is_babyai_world(name: str) -> bool:
    """Whether a world name names a Farama Minigrid BabyAI level (checked against minigrid by world/)."""
    return isinstance(name, str) and name.startswith(BABYAI_PREFIX)


PROFILES = ("default", "paper")  # ours (docs/decisions.md) or the paper's (docs/paper_settings.md)
FUSIONS = ("film", "concat")
CORES = ("stack", "gru")  # network.core
TEXT_ENCODERS = ("gru", "bow")  # network.text
TARGET_UPDATES = ("period", "polyak")
DECODINGS = ("greedy", "sample", "rephrase")  # generator.decoding
RATIO_COUNTS = ("env_frames", "transitions")
EXPLORATION_KINDS = ("apex", "linear")
RELABEL_STRATEGIES = ("none", "expert", "noisy", "learned")
LEARNED_WORDS = ("generator", "expert")  # relabel.words
# The fields that take one of a few words, by dotted path: `validate` and docs/configuration.md read this.
CHOICES: dict[str, tuple[str, ...]] = {
    "preset": PRESETS, "profile": PROFILES, "network.fusion": FUSIONS, "network.core": CORES,
    "network.text": TEXT_ENCODERS, "dqn.target_update": TARGET_UPDATES, "relabel.words": LEARNED_WORDS,
    "replay.ratio_counts": RATIO_COUNTS, "exploration.kind": EXPLORATION_KINDS,
    "relabel.strategy": RELABEL_STRATEGIES, "generator.decoding": DECODINGS,
}


class ConfigError(ValueError):
    """A config value that cannot work; the message names the field and the reason."""


# Every field has one comment line, its meaning: docs/configuration.md is generated from them
# (`make docs`); why a default is what it is lives in docs/decisions.md.
@dataclass(frozen=True)
class WorldConfig:
    name: str = "paper"  # the world: paper (10x10, 10 objects), small (tests) or a BabyAI level id
    room_size: int = 10  # interior cells per side; the outer wall is added around it
    n_objects: int = 10  # objects in the room, the goal among them
    colors: tuple[str, ...] = COLORS  # attribute values this world uses (subsets of the global tables)
    types: tuple[str, ...] = TYPES  # object types this world uses
    shades: tuple[str, ...] = SHADES  # shades this world uses
    sizes: tuple[str, ...] = SIZES  # sizes this world uses
    max_steps: int = 40  # steps before an episode times out (BabyAI: 0 = the level's own)
    view_size: int = 7  # side of the agent's egocentric view, in cells (odd)
    heldout_count: int = 60  # objects kept out of training goals (paper: 60 of 300)
    split_seed: int = 0  # seed of the train / held-out split of the objects
    reward_shaping: bool = False  # DQN+reward: 0.25 per matching attribute of the picked object


@dataclass(frozen=True)
class NetworkConfig:
    embed_dim: int = 8  # cell embedding width: a vector per (channel, value), summed (BabyAI 1.1 bag of words)
    conv_channels: tuple[int, ...] = (16, 32)  # channels of the view's conv layers
    frame_stack: int = 4  # past views stacked into the input (1: none)
    core: str = "stack"  # memory: stack (the last frame_stack views) | gru (a GRU over the whole episode; frame_stack 1)
    fusion: str = "film"  # how the instruction meets the view: film | concat
    film_blocks: int = 0  # residual FiLM blocks h + relu(FiLM(conv(h))) after the convs; 0: FiLM on the last conv
    text: str = "gru"  # instruction encoder: gru (a GRU over the words, in order) | bow (bag of words: summed word vectors, one tanh layer)
    word_embed_dim: int = 16  # word embedding of the instruction
    text_hidden: int = 32  # width of the instruction's features (the GRU's state, or the bag of words' layer)
    hidden: int = 64  # width of the Q head's hidden layer
    dueling: bool = True  # dueling head (value + advantages)
    head_init_scale: float = 0.01  # the head's output layers start scaled by this, biases at zero (Q ~ 0)

    @property
    def recurrent(self) -> bool:
        """The recurrent core: one view per step, trained on whole episodes (learning/recurrent.py)."""
        return self.core == "gru"


@dataclass(frozen=True)
class DQNConfig:
    batch_size: int = 256  # transitions per update (network.core=stack)
    sequence_batch: int = 16  # whole episodes per update (network.core=gru): ~300 transitions on the paper world
    lr: float = 5e-4  # Adam learning rate
    lr_decay_frames: int = 0  # > 0: lr falls linearly to lr * lr_end_fraction over this many env frames
    lr_end_fraction: float = 0.1  # where the lr decay ends, as a fraction of lr
    adam_eps: float = 1e-6  # Adam's epsilon
    gamma: float = 0.95  # discount per step (a wasted step costs 5% of the value: docs/decisions.md)
    n_step: int = 5  # steps of the n-step return (3 on the small world: docs/decisions.md)
    huber_delta: float = 1.0  # Huber loss threshold
    grad_clip: float = 10.0  # gradient norm clip
    target_update: str = "period"  # target network: period (hard copies) | polyak (soft)
    target_period: int = 750  # updates between hard target copies (48k env frames at batch 256, 4 samples/frame)
    polyak_tau: float = 0.005  # soft target step per update (target_update = polyak)
    double: bool = True  # double DQN targets
    average_tau: float = 0.001  # > 0: also keep a moving average of the weights, evaluated beside them
    compile: bool = True  # torch.compile the loss on a background thread (eager until ready, or for good)
    joint_online: bool = False  # one online forward over obs and next_obs stacked
    prefetch: bool = False  # sample the next batch on a thread during the update


@dataclass(frozen=True)
class ReplayConfig:
    capacity: int = 200_000  # transitions (frames), FIFO eviction by whole episodes
    alpha: float = 0.6  # priority exponent
    beta_start: float = 0.4  # importance-sampling exponent at the start
    beta_end: float = 1.0  # importance-sampling exponent after beta_frames
    beta_frames: int = 5_000_000  # frames over which beta anneals to beta_end
    min_size: int = 2_000  # transitions before learning starts
    samples_per_insert: float = 4.0  # replay ratio kept by the rate limiter (as in Reverb): samples per env frame
    ratio_counts: str = "env_frames"  # what one insert is: env_frames (originals only) | transitions
    timeouts_terminal: bool = False  # True: a time-out is stored as terminal (the paper's code), else it bootstraps
    priority_eps: float = 1e-3  # added to |TD error| for priorities
    checkpoint_replay: bool = True  # the replay in the learner's checkpoint: a resume keeps it (49 MiB and a 0.2 s pause at 200k: higher-bench checkpoint)


@dataclass(frozen=True)
class ExplorationConfig:
    kind: str = "apex"  # apex: a fixed epsilon per env slot | linear: one decaying epsilon
    eps_base: float = 0.4  # Ape-X: eps_i = eps_base ** (1 + apex_alpha * i / (N - 1))
    apex_alpha: float = 7.0  # Ape-X: spread of the epsilon ladder (7: rungs from 0.4 down to 0.4^8, mean 0.06)
    eps_start: float = 1.0  # linear: epsilon at frame 0
    eps_end: float = 0.05  # linear: epsilon after decay_frames
    decay_frames: int = 1_000_000  # linear: env frames of the decay
    warmup_frames: int = 0  # apex: every slot decays from 1.0 to its rung over this many env frames (0: none)
    repeat_max: int = 1  # ez-greedy: an exploratory action is held up to this many steps (1: plain)
    repeat_mu: float = 2.0  # ez-greedy: the zeta exponent of the hold length


@dataclass(frozen=True)
class GeneratorConfig:
    embed_dim: int = 16  # per-channel value embedding of the view
    conv_channels: tuple[int, ...] = (32, 64)  # channels of the view's conv layers
    word_embed_dim: int = 32  # word embedding of the decoder
    hidden: int = 128  # GRU decoder width
    max_len: int = 12  # decoding cap, END included
    lr: float = 1e-3  # Adam learning rate
    lr_decay_updates: int = 0  # > 0: lr falls linearly to lr * lr_end_fraction over this many generator updates
    lr_end_fraction: float = 0.1  # where the lr decay ends, as a fraction of lr
    batch_size: int = 64  # pairs per update
    capacity: int = 20_000  # (observation, instruction) pairs kept, FIFO
    val_fraction: float = 0.1  # pairs held out to measure the generator (the gate's input)
    n_min: int = 1000  # gate: pairs needed before relabelling (paper: 1000)
    front_cell_shortcut: bool = True  # feed the front cell's channel embeddings, side by side, straight to the decoder
    min_accuracy: float = 0.5  # gate: validation exact match needed; 0 = the paper's ungated variant
    beam_width: int = 0  # > 1: greedy words that do not parse give way to the likeliest of this many beams that does
    decoding: str = "greedy"  # a relabel's words: greedy (the likeliest) | sample (drawn, as the expert draws a phrasing) | rephrase (drawn where they name the greedy words' object)
    temperature: float = 1.0  # decoding=sample or rephrase: words drawn from softmax(logits / temperature)
    top_p: float = 1.0  # decoding=sample or rephrase: draw only among the likeliest words that hold this much probability (nucleus)
    agreement_draws: int = 0  # instructions drawn per relabel to measure how sure the generator is of its object (0: none)
    min_agreement: float = 0.0  # a relabel is dropped when fewer than this share of those draws name its object
    updates_per_kframe: float = 10.0  # generator updates per 1000 env frames of original episodes
    trained_accuracy: float = 0.0  # > 0: from this validation exact match up, train at trained_updates_per_kframe
    trained_updates_per_kframe: float = 2.0  # the pace while the generator is at trained_accuracy or above
    gated_updates_per_kframe: float = 0.0  # > 0: the pace while the gate is shut (0: updates_per_kframe)
    eval_every_updates: int = 200  # validation exact match (the gate's input) every this many updates


@dataclass(frozen=True)
class RelabelConfig:
    strategy: str = "none"  # wrong picks relabelled by: none | expert | noisy | learned
    noise_p: float = 0.2  # noisy expert: each attribute swapped to another value with this probability
    # BabyAI levels record several outcomes per episode, FetchAttr one; more than this: a random choice.
    max_per_episode: int = 4  # relabelled copies of one failed episode at most, one per distinct outcome
    held_while_gated: int = 0  # learned: the newest failures kept while the gate is shut, relabelled when it opens
    withheld_while_gated: bool = False  # learned: failures it cannot relabel yet are kept out of the replay (their frames still count)
    words: str = "generator"  # learned: whose words a relabel carries once the gate is open (expert: an ablation)


@dataclass(frozen=True)
class EvalConfig:
    every_frames: int = 50_000  # env frames between greedy evaluations
    episodes: int = 256  # greedy episodes per goal set (training, held-out), one per environment


@dataclass(frozen=True)
class Config:
    preset: str = "higher"  # the paper's method (see PRESETS)
    profile: str = "default"  # default (ours) | paper (the paper's settings)
    world: WorldConfig = field(default_factory=WorldConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    dqn: DQNConfig = field(default_factory=DQNConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    generator: GeneratorConfig = field(default_factory=GeneratorConfig)
    relabel: RelabelConfig = field(default_factory=RelabelConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    actors: int = 2  # actor processes
    envs_per_actor: int = 32  # environments each actor steps together
    frames: int = 5_000_000  # env frames budget of the run
    seed: int = 0  # the run's seed; every component's seed derives from it
    device: str = "auto"  # the learner's torch device: auto (CUDA when present), cpu or cuda[:N]
    actor_device: str = "cpu"  # the actors' policy device: cpu, auto or cuda[:N]
    torch_threads: int = 0  # the learner's torch threads; 0: the layout's share (launch/layout.py)
    weights_every: int = 20  # learner updates between weight publications
    stats_every_s: float = 2.0  # seconds between stats messages and metrics records
    checkpoint_every_s: float = 120.0  # seconds between checkpoints
    role_grace_s: float = 30.0  # a role silent this long is dead and its number free (a link cut shorter keeps it)
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


def _is_int(value: Any) -> bool:  # an override may hand over any value; a bool is not an integer here
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def validate_world(w: WorldConfig) -> None:
    """Refuse a world that cannot be built, naming the field. Also called by the world itself, which
    is built on its own by tests, benchmarks and the Gymnasium view."""
    if not isinstance(w, WorldConfig):
        raise ConfigError(f"world: expected a WorldConfig, got {type(w).__name__}")
    if is_babyai_world(w.name):  # the level itself is checked against minigrid when it is built
        _check(_is_int(w.max_steps) and w.max_steps >= 0,
               f"world.max_steps: must be an integer >= 0 (0: the level's own), got {w.max_steps!r}")
        _check(w.view_size == 7, f"world.view_size: BabyAI levels show a 7x7 view, got {w.view_size!r}")
        _check(not w.reward_shaping, "world.reward_shaping: not defined on BabyAI levels (the level gives the reward)")
        return
    for name in ("room_size", "n_objects", "max_steps", "view_size", "heldout_count", "split_seed"):
        value = getattr(w, name)
        _check(_is_int(value), f"world.{name}: expected an integer, got {value!r}")
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
    for path, allowed in CHOICES.items():
        value = functools.reduce(getattr, path.split("."), cfg)
        _check(value in allowed, f"{path}: must be one of {', '.join(allowed)}, got {value!r}")
    validate_world(cfg.world)
    w, n = cfg.world, cfg.network
    _check(n.frame_stack >= 1, f"network.frame_stack: must be >= 1, got {n.frame_stack}")
    _check(not n.recurrent or n.frame_stack == 1,
           f"network.frame_stack: network.core=gru reads one view per step, set it to 1 (got {n.frame_stack})")
    _check(n.head_init_scale > 0, f"network.head_init_scale: must be > 0, got {n.head_init_scale}")
    _check(len(n.conv_channels) >= 1, "network.conv_channels: needs at least one layer")
    _check(n.film_blocks >= 0, f"network.film_blocks: must be >= 0 (0: FiLM on the last conv), got {n.film_blocks}")
    _check(n.film_blocks == 0 or n.fusion == "film",
           f"network.film_blocks: {n.film_blocks} block(s) need network.fusion=film, got {n.fusion!r}")
    d = cfg.dqn
    for name in ("batch_size", "sequence_batch", "n_step"):
        _check(getattr(d, name) >= 1, f"dqn.{name}: must be >= 1, got {getattr(d, name)}")
    _check(d.lr > 0, f"dqn.lr: must be > 0, got {d.lr}")
    _check(d.lr_decay_frames >= 0, f"dqn.lr_decay_frames: must be >= 0 (0: constant lr), got {d.lr_decay_frames}")
    _check(0.0 < d.lr_end_fraction <= 1.0, f"dqn.lr_end_fraction: must be in (0, 1], got {d.lr_end_fraction}")
    _check(0.0 <= d.gamma <= 1.0, f"dqn.gamma: must be in [0, 1], got {d.gamma}")
    _check(0.0 < d.polyak_tau <= 1.0, f"dqn.polyak_tau: must be in (0, 1], got {d.polyak_tau}")
    _check(0.0 <= d.average_tau <= 1.0, f"dqn.average_tau: must be in [0, 1] (0: no average), got {d.average_tau}")
    r = cfg.replay
    _check(r.capacity >= 2 * (w.max_steps + 1), f"replay.capacity: must hold at least two episodes, got {r.capacity}")
    _check(0 < r.min_size <= r.capacity, f"replay.min_size: must be in (0, capacity={r.capacity}], got {r.min_size}")
    _check(r.alpha >= 0 and 0 <= r.beta_start <= 1 and 0 <= r.beta_end <= 1, "replay: alpha >= 0 and betas in [0, 1]")
    _check(r.samples_per_insert > 0, f"replay.samples_per_insert: must be > 0, got {r.samples_per_insert}")
    e = cfg.exploration
    _check(0 <= e.eps_base <= 1 and 0 <= e.eps_end <= e.eps_start <= 1, "exploration: epsilons must lie in [0, 1], end <= start")
    _check(e.warmup_frames >= 0, f"exploration.warmup_frames: must be >= 0, got {e.warmup_frames}")
    _check(e.repeat_max >= 1, f"exploration.repeat_max: must be >= 1, got {e.repeat_max}")
    _check(e.repeat_mu > 0, f"exploration.repeat_mu: must be > 0, got {e.repeat_mu}")
    g = cfg.generator
    _check(0 < g.val_fraction < 1, f"generator.val_fraction: must be in (0, 1), got {g.val_fraction}")
    _check(0 <= g.min_accuracy <= 1, f"generator.min_accuracy: must be in [0, 1], got {g.min_accuracy}")
    _check(g.lr_decay_updates >= 0, f"generator.lr_decay_updates: must be >= 0 (0: constant lr), got {g.lr_decay_updates}")
    _check(0.0 < g.lr_end_fraction <= 1.0, f"generator.lr_end_fraction: must be in (0, 1], got {g.lr_end_fraction}")
    _check(g.temperature > 0, f"generator.temperature: must be > 0, got {g.temperature}")
    _check(0 < g.top_p <= 1, f"generator.top_p: must lie in (0, 1], got {g.top_p}")
    for name in ("agreement_draws", "beam_width"):
        _check(_is_int(getattr(g, name)) and 0 <= getattr(g, name) <= MAX_AGREEMENT_DRAWS,
               f"generator.{name}: must be an integer in [0, {MAX_AGREEMENT_DRAWS}], got {getattr(g, name)!r}")
    _check(0 <= g.min_agreement <= 1, f"generator.min_agreement: must lie in [0, 1], got {g.min_agreement}")
    _check(g.min_agreement == 0 or g.agreement_draws > 0, "generator.min_agreement: needs generator.agreement_draws > 0")
    _check(g.agreement_draws == 0 or g.decoding != "sample", "generator.agreement_draws: not with generator.decoding=sample")
    _check(g.max_len >= 6, f"generator.max_len: must be >= 6 to hold an instruction, got {g.max_len}")
    _check(g.capacity >= 10, f"generator.capacity: must be >= 10, got {g.capacity}")
    _check(0 <= g.trained_accuracy <= 1,
           f"generator.trained_accuracy: must be in [0, 1] (0: off), got {g.trained_accuracy}")
    for pace in ("updates_per_kframe", "trained_updates_per_kframe", "gated_updates_per_kframe"):
        _check(getattr(g, pace) >= 0, f"generator.{pace}: must be >= 0, got {getattr(g, pace)}")
    _check(g.eval_every_updates >= 1, f"generator.eval_every_updates: must be >= 1, got {g.eval_every_updates}")
    rl = cfg.relabel
    _check(0 <= rl.noise_p <= 1, f"relabel.noise_p: must be in [0, 1], got {rl.noise_p}")
    for name, low, high in (("max_per_episode", 1, MAX_OUTCOMES), ("held_while_gated", 0, MAX_HELD_WHILE_GATED)):
        value = getattr(rl, name)
        _check(_is_int(value) and low <= value <= high, f"relabel.{name}: must be an integer in [{low}, {high}], got {value!r}")
    for name, off in (("held_while_gated", 0), ("words", "generator"), ("withheld_while_gated", False)):
        _check(getattr(rl, name) == off or rl.strategy == "learned",
               f"relabel.{name}: only a learned relabeller has a gate to wait for, not {rl.strategy!r}")
    for name in ("actors", "envs_per_actor", "frames"):
        _check(getattr(cfg, name) >= 1, f"{name}: must be >= 1, got {getattr(cfg, name)}")
    for name in ("device", "actor_device"):
        value = getattr(cfg, name)
        _check(value in ("auto", "cpu", "cuda") or (value.startswith("cuda:") and value[5:].isdigit()),
               f"{name}: must be auto, cpu, cuda or cuda:N, got {value!r}")
    _check(cfg.role_grace_s > cfg.stats_every_s,
           f"role_grace_s: must exceed stats_every_s ({cfg.stats_every_s}: the heartbeat), got {cfg.role_grace_s}")
    _check(cfg.torch_threads >= 0, f"torch_threads: must be >= 0 (0: the layout decides), got {cfg.torch_threads}")
    _check(cfg.weights_every >= 1, f"weights_every: must be >= 1, got {cfg.weights_every}")
