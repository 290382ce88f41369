"""The one-place knowledge: the world spec, the agent builder (seeds, cadences, generator pace), the
limiter's tolerance, Learner's counters, the config's override / from_dict / validate; and the house's
shape: the import graph's layers and cycles (every import, function-level ones too), and file sizes."""
from __future__ import annotations

import ast
import collections
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from higher_dist.config import ConfigError, WorldConfig, from_dict, override, validate
from higher_dist.config_presets import make_config, small_world
from higher_dist.learning.agent import AgentBuilder, Cadence, GeneratorPace, Seeds, train_generator
from higher_dist.learning.learner import Learner
from higher_dist.learning.rate_limiter import SamplesPerInsertLimiter
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.world import language
from higher_dist.world.grid import BatchedFetchAttr
from higher_dist.world.spec import (DEFAULT_SPEC, N_ACTIONS, OUTCOME_NAMES, SUCCESS, TIMEOUT, VIEW_CHANNEL_VALUES,
                                    WRONG_PICK, WorldSpec)

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "higher_dist"


# -- the world spec ---------------------------------------------------------------------------------

def test_spec_is_made_from_the_world_config():
    small = WorldSpec.of(small_world())
    assert small.view_size == 7 and small.max_steps == 20
    assert small.mission_len == language.MISSION_LEN and small.vocab_size == len(language.VOCAB)
    assert small.channel_values == VIEW_CHANNEL_VALUES == DEFAULT_SPEC.channel_values  # global tables
    assert small.world_values[0] == (0, 1)  # red, green
    assert DEFAULT_SPEC.world_values[0] == tuple(range(6))
    assert WorldSpec.of(replace(WorldConfig(), view_size=9)).view_shape == (9, 9, 4)
    assert (SUCCESS, WRONG_PICK, TIMEOUT) == (0, 1, 2) and len(OUTCOME_NAMES) == 3 and N_ACTIONS == 4


def test_every_cell_the_world_shows_is_allowed_by_its_spec():
    for world in (WorldConfig(), small_world()):
        spec = WorldSpec.of(world)
        allowed = spec.cell_allowed()
        env = BatchedFetchAttr(world, 16, seed=3)
        view, _ = env.reset()
        rng = np.random.default_rng(0)
        for _ in range(60):
            for c in range(4):
                assert allowed[c, view[..., c]].all(), (world.name, c)
            view = env.step(rng.integers(4, size=16)).view


def test_networks_replay_and_generator_read_the_spec():
    cfg = make_config("higher", "small", **{"world.view_size": 5})
    core = Learner(cfg)
    assert core.replay.view_size == 5 and core.replay.mission_len == core.spec.mission_len
    assert core.dqn.online.view.view_size == 5
    assert core.dqn.online.text.embed.num_embeddings == core.spec.vocab_size
    strategy = AgentBuilder(cfg).relabel_strategy()
    assert strategy.trainer.model.view_size == 5
    assert strategy.trainer.dataset.views.shape[1:] == (5, 5, 4)


# -- the builder --------------------------------------------------------------------------------------

def test_seeds_are_derived_once_and_distinct():
    s = Seeds(3)
    streams = [s.learner_torch, s.learner_init, s.learner_replay, *vars(s.relabeler).values(),
               *(s.actor_env_seeds(i, 1)[0] for i in range(8))]
    assert len(set(streams)) == len(streams)
    assert s.evaluation_env_seeds(100, 4) != s.evaluation_env_seeds(200, 4)
    a, b = AgentBuilder(make_config("her", "small", seed=3)), AgentBuilder(make_config("her", "small", seed=3))
    ca, cb = a.collector(1), b.collector(1)
    assert np.array_equal(ca.observation()[0], cb.observation()[0])
    assert not np.array_equal(ca.observation()[0], a.collector(0).observation()[0])


def test_cadence_fires_once_per_multiple_and_resumes_mid_way():
    c = Cadence(100)
    assert [n for n in (0, 50, 99, 100, 101, 250, 260, 300) if c.due(n)] == [100, 250, 300]
    assert not Cadence(100, start=250).due(280) and Cadence(100, start=250).due(300)


def test_generator_pace_is_per_frame_and_forgives_what_cannot_run():
    pace = GeneratorPace(updates_per_kframe=50)
    pace.add_frames(999)
    assert pace.owed == 49
    pace.settle(40)
    pace.add_frames(1001)
    assert pace.owed == 60

    class Untrainable:
        def train(self, n):
            return {}

    assert train_generator(Untrainable(), pace) == 0 and pace.owed == 0  # forgiven, not banked

    class Counting:
        steps = 0

        def train(self, n):
            self.steps += n
            return {"loss": 1.0}

    strategy = Counting()
    pace.add_frames(2000)
    assert train_generator(strategy, pace, max_updates=30) == 30 and pace.owed == 70
    assert train_generator(strategy, pace) == 70 and strategy.steps == 100


def test_a_trained_generator_earns_the_trained_pace_until_its_accuracy_falls_back():
    pace = GeneratorPace(updates_per_kframe=10, trained_accuracy=0.9, trained_updates_per_kframe=2)

    class Measured:
        generator_accuracy = None
        gate_open = None

        def train(self, n):
            return {"loss": 1.0}

    strategy = Measured()
    pace.add_frames(1000)
    assert train_generator(strategy, pace) == 10 and not pace.trained  # not measured yet: full pace
    strategy.generator_accuracy = 0.95
    pace.add_frames(1000)
    assert train_generator(strategy, pace) == 10 and pace.trained  # these frames came before it was measured
    pace.add_frames(3000)
    assert pace.owed == 6 and train_generator(strategy, pace) == 6
    strategy.generator_accuracy = 0.85  # a shift in what the agent picks: back to the full pace
    pace.add_frames(1000)
    assert train_generator(strategy, pace) == 2 and not pace.trained
    pace.add_frames(1000)
    assert pace.owed == 10
    again = GeneratorPace(updates_per_kframe=10, trained_accuracy=0.9, trained_updates_per_kframe=2)
    again.load_state_dict(pace.state_dict())
    assert (again.owed, again.frames_trained, again.trained) == (10, 4000, False)
    off = GeneratorPace(updates_per_kframe=10)  # trained_accuracy 0: one pace whatever the accuracy
    off.follow(1.0)
    off.add_frames(1000)
    assert not off.trained and off.owed == 10


def test_a_shut_gate_earns_the_gated_pace_and_its_frames_keep_it_after_the_gate_opens():
    pace = GeneratorPace(updates_per_kframe=10, trained_accuracy=0.9, trained_updates_per_kframe=2,
                         gated_updates_per_kframe=40)

    class Gated:
        generator_accuracy, gate_open = None, False

        def train(self, n):
            return {"loss": 1.0}

    strategy = Gated()
    assert pace.gated and pace.updates_per_kframe == 40  # the gate starts shut
    pace.add_frames(1000)
    assert train_generator(strategy, pace) == 40 and pace.gated
    strategy.generator_accuracy, strategy.gate_open = 0.95, False  # right, but too few pairs: still shut
    pace.add_frames(500)
    assert train_generator(strategy, pace) == 20 and pace.gated and pace.updates_per_kframe == 40  # shut comes first
    strategy.gate_open = True
    pace.add_frames(1000)
    assert train_generator(strategy, pace) == 40 and not pace.gated and pace.trained  # came while shut
    pace.add_frames(1000)
    assert pace.updates_per_kframe == 2 and train_generator(strategy, pace) == 2
    strategy.generator_accuracy = 0.5  # a measurement below the gate's threshold shuts it again
    strategy.gate_open = False
    pace.add_frames(1000)
    assert train_generator(strategy, pace) == 2 and pace.gated
    pace.add_frames(1000)
    assert pace.owed == 40 and (pace.frames_gated, pace.frames_trained) == (3500, 2000)
    again = GeneratorPace(updates_per_kframe=10, trained_accuracy=0.9, trained_updates_per_kframe=2,
                          gated_updates_per_kframe=40)
    again.load_state_dict(pace.state_dict())
    assert (again.owed, again.gated, again.frames_gated) == (40, True, 3500)
    expert = GeneratorPace(updates_per_kframe=10, gated_updates_per_kframe=40)
    expert.follow(None, None)  # no generator, no gate: the plain pace
    expert.add_frames(1000)
    assert not expert.gated and expert.owed == 10
    old = GeneratorPace(updates_per_kframe=10, gated_updates_per_kframe=40)
    old.load_state_dict({"frames": 5000, "settled": 50})  # a checkpoint from before the gated pace
    assert not old.gated and old.owed == 0


def test_the_builder_paces_the_generator_as_configured():
    cfg = make_config("higher", "small", **{"generator.trained_accuracy": 0.97,
                                            "generator.trained_updates_per_kframe": 1.5})
    pace = AgentBuilder(cfg).generator_pace()
    assert (pace.rate, pace.trained_accuracy, pace.trained_rate) == (50 / 1000, 0.97, 1.5 / 1000)
    with pytest.raises(ConfigError, match="generator.trained_accuracy"):
        make_config("higher", "small", **{"generator.trained_accuracy": 1.5})
    gated = AgentBuilder(make_config("higher", "small", **{"generator.gated_updates_per_kframe": 80.0})).generator_pace()
    assert gated.gated_rate == 80 / 1000 and gated.gated
    with pytest.raises(ConfigError, match="generator.gated_updates_per_kframe"):
        make_config("higher", "small", **{"generator.gated_updates_per_kframe": -1.0})


def test_runner_trains_the_generator_at_the_configured_pace():
    from higher_dist.learning.runner import SingleProcessRunner

    cfg = make_config("higher", "small", frames=2000, actors=1, **{"generator.updates_per_kframe": 10.0,
                                                                  "replay.min_size": 100,
                                                                  "replay.samples_per_insert": 0.5})
    runner = SingleProcessRunner(cfg)
    runner.run(frames=2000, metrics_every=2000)
    # Every frame of an original episode counts once; updates owed are 10 per 1000 such frames.
    assert runner.pace.frames == runner.core.frames
    assert runner.pace.settled == int(runner.core.frames * 10 / 1000)


def test_runner_trains_a_shut_gates_generator_at_the_gated_pace():
    from higher_dist.learning.runner import SingleProcessRunner

    cfg = make_config("higher", "small", frames=2000, actors=1, **{"generator.updates_per_kframe": 10.0,
                                                                  "generator.gated_updates_per_kframe": 40.0,
                                                                  "replay.min_size": 100,
                                                                  "replay.samples_per_insert": 0.5})
    runner = SingleProcessRunner(cfg)
    runner.run(frames=2000, metrics_every=2000)
    # 2000 frames hold far fewer than the gate's 100 pairs: every frame came while it was shut.
    assert not runner.relabeler.gate_open and runner.pace.frames_gated == runner.pace.frames == runner.core.frames
    assert runner.pace.settled == int(runner.core.frames * 40 / 1000)


# -- the limiter and the core's counters ------------------------------------------------------------

def test_limiter_tolerance_blocks_each_side_only_past_the_slack():
    lim = SamplesPerInsertLimiter(samples_per_insert=2.0, min_size=100, tolerance=50)
    assert lim.can_insert() and not lim.can_sample(replay_size=50, batch_size=10)  # filling up
    lim.record_insert(150)  # 50 past min_size: the learner owes 100 samples
    assert lim.can_sample(150, 10) and lim.can_insert() is False  # 100 owed > 50 slack: stop inserting
    lim.record_sample(60)  # owes 40
    assert lim.can_insert() and lim.can_sample(150, 10)
    lim.record_sample(100)  # 60 ahead of the ratio
    assert not lim.can_sample(150, 10)  # deficit -60 < batch 10 - slack 50
    assert lim.can_sample(150, 0) is False and lim.ratio == pytest.approx(160 / 150)


def test_the_learner_counts_original_and_relabelled_episodes_apart():
    cfg = make_config("her", "small", **{"replay.min_size": 50})
    core = Learner(cfg)
    episodes = real_episodes(cfg.world, 12, seed=1, relabelled=True)
    core.add_episodes(episodes)
    originals = [ep for ep in episodes if not ep.relabelled]
    assert core.episodes == len(originals)
    assert core.relabelled_episodes == len(episodes) - len(originals) > 0
    assert core.frames == sum(ep.length for ep in originals)
    assert core.success_rate_train == pytest.approx(np.mean([ep.outcome == SUCCESS for ep in originals]))
    metrics = core.metrics()
    assert metrics["frames"] == core.frames and metrics["replay_relabelled"] == sum(ep.length for ep in episodes if ep.relabelled)


# -- config ---------------------------------------------------------------------------------------------

def test_override_from_dict_and_validate_name_the_field():
    cfg = make_config("her", "small")
    assert override(cfg, **{"dqn.lr": 0.01}).dqn.lr == 0.01
    with pytest.raises(ConfigError, match="dqn.nope"):
        override(cfg, **{"dqn.nope": 1})
    d = cfg.to_dict()
    assert from_dict(d) == cfg
    with pytest.raises(ConfigError, match="dqn.batch_size"):
        from_dict({**d, "dqn": {**d["dqn"], "batch_size": "big"}})
    with pytest.raises(ConfigError, match="unknown fields"):
        from_dict({**d, "surprise": 1})
    with pytest.raises(ConfigError, match="generator.updates_per_kframe"):
        validate(override(cfg, **{"generator.updates_per_kframe": -1.0}))
    with pytest.raises(ConfigError, match="replay.min_size"):
        validate(override(cfg, **{"replay.min_size": 0}))


# -- the import graph ---------------------------------------------------------------------------------

# Bottom to top. A module may import its own unit (a top-level module, or a folder) and units of lower
# layers, never a unit of its own layer or above: every arrow points down.
LAYERS = (
    ("config", "metrics", "paths"),
    ("config_presets", "resume"),
    ("config_flags",),
    ("world",),
    ("learning",),
    ("wire",),
    ("rundir",),
    ("launch",),
    ("roles",),
    ("render_babyai", "tally"),  # below render, which draws and tallies through them
    ("analysis", "render"),
    ("plot", "reproduce", "bench"),
    ("cli", "docs_gen"),
)
RANK = {unit: i for i, layer in enumerate(LAYERS) for unit in layer}
PURE = ("world", "learning")  # the algorithm: no transport, no terminal UI, no processes
NOT_IN_PURE = ("zmq", "rich", "multiprocessing", "psutil", "subprocess", "socket")


def _modules() -> dict[str, Path]:
    mods = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return mods


def _imports(name: str, path: Path, mods: dict[str, Path]) -> list[str]:
    """Every module `name` imports, at any depth of its code (function-level imports included)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            out += [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
    return out


def _unit(module: str) -> str:
    return module.split(".")[1] if module.count(".") else ""


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {name: {t for t in _imports(name, path, mods) if t in mods and t != name} for name, path in mods.items()}


def test_every_unit_has_a_layer_and_every_arrow_points_down():
    graph = _graph()
    units = {_unit(name) for name in graph} - {""}
    assert units <= set(RANK), f"give these a layer in LAYERS: {sorted(units - set(RANK))}"
    upward = [f"{a} -> {b}" for a, targets in graph.items() for b in targets
              if _unit(a) and _unit(b) and _unit(a) != _unit(b) and RANK[_unit(b)] >= RANK[_unit(a)]]
    assert not upward, "imports that point up or sideways:\n" + "\n".join(sorted(upward))


def test_the_import_graph_has_no_cycles():
    graph = _graph()
    state: dict[str, int] = collections.defaultdict(int)  # 0 new, 1 on the path, 2 done
    cycles = []

    def visit(node: str, path: list[str]) -> None:
        state[node], path = 1, path + [node]
        for nxt in sorted(graph[node]):
            if state[nxt] == 1:  # on the current path: a cycle
                cycles.append(" -> ".join(path[path.index(nxt):] + [nxt]))
            elif state[nxt] == 0:
                visit(nxt, path)
        state[node] = 2

    for node in sorted(graph):
        if state[node] == 0:
            visit(node, [])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_pure_layers_import_no_transport_and_world_nothing_above_it():
    mods = _modules()
    for name, path in mods.items():
        if _unit(name) in PURE:
            for target in _imports(name, path, mods):
                assert not target.startswith(NOT_IN_PURE), (name, target)
                if _unit(name) == "world":
                    assert not target.startswith("higher_dist.learning"), (name, target)


def test_the_layering_check_sees_function_level_and_relative_imports(tmp_path):
    path = tmp_path / "probe.py"
    path.write_text("def f():\n    from higher_dist.cli import main\n    from . import grid\n")
    mods = {"higher_dist.cli": path, "higher_dist.world.grid": path}
    assert _imports("higher_dist.world.probe", path, mods) == ["higher_dist.cli", "higher_dist.world.grid"]


def test_every_python_file_is_under_400_lines():
    long = {str(p.relative_to(ROOT)): n for folder in ("higher_dist", "tests") for p in (ROOT / folder).rglob("*.py")
            if (n := len(p.read_text().splitlines())) >= 400}
    assert not long, f"split these: {long}"

