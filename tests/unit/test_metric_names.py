"""Metric and stat names have one home, higher_dist/metrics.py: writers and readers use its constants, every
name a writer emits is declared there, and every name a reader reads is one some writer emits."""
from __future__ import annotations

import ast
import pathlib

import pytest

from higher_dist import metrics as m
from higher_dist.config_presets import make_config
from higher_dist.learning.hindsight.relabel import make_relabel_strategy
from higher_dist.learning.learner import Learner
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.roles.registry import RoleRegistry

SRC = pathlib.Path(__file__).resolve().parents[2] / "higher_dist"
DECLARED = {value for name, value in vars(m).items() if name.isupper() and isinstance(value, str)}
PREFIXES = {value for name, value in vars(m).items() if name.endswith("_PREFIX")}
# Modules that write or read metric records and role stats (checkpoint layouts and wire message fields,
# which reuse some of the same words, are not metric dicts: see _metric_dict_keys).
METRIC_MODULES = sorted({*SRC.glob("roles/*.py"), *SRC.glob("analysis/*.py"), SRC / "reproduce/archive.py",
                         SRC / "reproduce/figures.py", SRC / "reproduce/status.py",
                         SRC / "learning/dqn.py",
                         SRC / "learning/hindsight/relabel.py", SRC / "learning/learner.py",
                         SRC / "learning/runner.py", SRC / "learning/acting.py", SRC / "learning/agent.py",
                         SRC / "plot.py"})
READERS = sorted({*SRC.glob("analysis/*.py"), *SRC.glob("reproduce/*.py"), SRC / "roles/dashboard_view.py",
                  SRC / "plot.py"})
# Functions that build a metric record, a stats message or a role row, and the names of variables that hold one.
METRIC_FUNCTIONS = {"metrics", "_metrics", "record", "_own_row", "table", "telemetry", "update", "evaluate"}
METRIC_VARIABLES = {"record", "rec", "r", "row", "stats", "metrics", "relabeler", "values", "counters", "last_metrics"}


def _receiver(node: ast.AST) -> str:
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else ""


def _metric_dict_keys(tree: ast.AST):
    """(line, literal) of every string literal used as a key of a metric dict: keys of dicts built in a
    METRIC_FUNCTIONS function or passed to stats()/heartbeat(), subscripts and .get()s of METRIC_VARIABLES,
    and dict(zip((literals), ...))."""
    for fn in [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]:
        in_metric_fn = fn.name in METRIC_FUNCTIONS
        for node in ast.walk(fn):
            keys = []
            if isinstance(node, ast.Dict) and in_metric_fn:
                keys = node.keys
            elif isinstance(node, ast.Call) and _receiver(node.func) in ("stats", "heartbeat"):
                keys = [k for a in node.args if isinstance(a, ast.Dict) for k in a.keys]
            elif isinstance(node, ast.Subscript) and _receiver(node.value) in METRIC_VARIABLES:
                keys = [node.slice]
            elif (isinstance(node, ast.Call) and _receiver(node.func) in ("get", "pop")
                  and _receiver(node.func.value) in METRIC_VARIABLES and node.args):
                keys = [node.args[0]]
            elif isinstance(node, ast.Call) and _receiver(node.func) == "zip":
                keys = [e for a in node.args if isinstance(a, ast.Tuple) for e in a.elts]
            for k in keys:
                if isinstance(k, ast.Constant) and isinstance(k.value, str):
                    yield k.lineno, k.value


def _constants_used(path: pathlib.Path) -> set[str]:
    """Names X of every `m.X` (metrics imported as m or as metrics) in a module."""
    tree = ast.parse(path.read_text())
    return {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
            and n.value.id in ("m", "metrics", "names") and n.attr.isupper()}


def test_no_metric_name_is_written_as_a_literal():
    found = [f"{path.relative_to(SRC.parent)}:{line}: {key!r}" for path in METRIC_MODULES
             for line, key in _metric_dict_keys(ast.parse(path.read_text()))
             if key in DECLARED or any(key.startswith(p) for p in PREFIXES)]
    assert not found, "use the constant of higher_dist/metrics.py:\n" + "\n".join(found)


def test_the_literal_check_sees_each_kind_of_metric_dict():
    source = '''
def metrics(self):
    return {"loss": 1}
def run(client, record, relabeler):
    client.stats({"frames": 1})
    record["q_mean"], relabeler.get("relabels_per_s")
    dict(zip(("td_abs_mean",), (1,)))
def state_dict(self):
    return {"updates": 1}
'''
    keys = [key for _, key in _metric_dict_keys(ast.parse(source))]
    assert keys == ["loss", "frames", "q_mean", "relabels_per_s", "td_abs_mean"]


def test_every_metric_constant_used_in_the_source_is_declared():
    unknown = [f"{path.relative_to(SRC.parent)}: m.{name}" for path in sorted(SRC.rglob("*.py"))
               for name in _constants_used(path) if not hasattr(m, name)]
    assert not unknown


@pytest.fixture(scope="module")
def trained_core():
    cfg = make_config("her", "small", **{"replay.min_size": 50})
    core = Learner(cfg)
    core.add_episodes(real_episodes(cfg.world, 12, seed=1, relabelled=True))
    core.train_available(max_updates=2)
    assert core.updates > 0
    return cfg, core


def test_a_dqn_update_reports_exactly_the_declared_keys(trained_core):
    _, core = trained_core
    assert set(core.last_metrics) == set(m.DQN_KEYS)


@pytest.mark.parametrize("strategy", ["none", "expert", "noisy", "learned"])
def test_every_relabel_strategy_reports_exactly_the_declared_keys(strategy):
    cfg = make_config("higher" if strategy == "learned" else "her", "small",
                      **{"relabel.strategy": strategy})
    assert list(make_relabel_strategy(cfg, seed=0).metrics()) == list(m.RELABEL_KEYS)


def _emitted_record(cfg, core) -> dict:
    return {**core.metrics(), **RoleRegistry().telemetry({m.ROW_ROLE: "learner"}, 0, {}),
            **make_relabel_strategy(cfg, seed=0).metrics()}


def test_every_key_a_writer_emits_is_declared(trained_core):
    cfg, core = trained_core
    undeclared = [k for k in _emitted_record(cfg, core)
                  if k not in DECLARED and not any(k.startswith(p) for p in PREFIXES)]
    assert not undeclared
    rows = RoleRegistry().telemetry({m.ROW_ROLE: "learner"}, 0, {})[m.ROLES]
    assert rows and all(set(row) <= set(m.ROLE_ROW_KEYS) for row in rows)


def test_every_key_a_reader_reads_is_emitted_by_a_writer(trained_core):
    """Readers (dashboard, analysis, reproduce, plot) read names a writer emits: the record's, the
    evaluation's, the learner role's own fields and the roles table's columns."""
    cfg, core = trained_core
    emitted = set(_emitted_record(cfg, core)) | set(m.ROLE_ROW_KEYS)
    # What needs a running learner: the evaluation's keys (acting.py, roles/evaluator.py), the learner
    # role's own fields (roles/learner.py: record()) and the record's time (rundir.py), read from their source.
    for writer in ("learning/acting.py", "roles/evaluator.py", "roles/learner.py", "rundir.py"):
        emitted |= {getattr(m, n) for n in _constants_used(SRC / writer) if isinstance(getattr(m, n), str)}
    for key in (m.SUCCESS_EVAL_TRAIN, m.SUCCESS_EVAL_HELDOUT):
        for suffix in ("", m.AVERAGED_SUFFIX):
            emitted |= {key + suffix, key + suffix + m.SE_SUFFIX}
    not_emitted = [f"{path.relative_to(SRC.parent)}: m.{name} = {getattr(m, name)!r}" for path in READERS
                   for name in sorted(_constants_used(path))
                   if isinstance(getattr(m, name), str) and not name.endswith(("_PREFIX", "_SUFFIX"))
                   and getattr(m, name) not in emitted]
    assert not not_emitted, "\n".join(not_emitted)
