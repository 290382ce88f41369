"""Every `--help` of every console script (pyproject.toml's [project.scripts], and each `higher-bench`
subcommand) states the defaults the code uses. A help text names a default as "(default: X)"; X is
checked against the option's argparse default, or, where that is None (worked out at run time), against
the value the code falls back to (USED) or, where it is no single value, against a phrase checked below.
"""
from __future__ import annotations

import argparse
import importlib
import re
import tomllib
from pathlib import Path

import pytest

from higher_dist.config import Config
from higher_dist.config_flags import config_from_args
from higher_dist.config_presets import make_config

ROOT = Path(__file__).resolve().parents[2]
STATED = re.compile(r"\(default: ([^()]*(?:\([^()]*\)[^()]*)*)\)")
ARGV = {"higher-plot": ["RUN"], "higher-keys": ["DIR"], "higher-render": ["RUN"]}  # required positionals
REQUIRED = {"--run-dir": "RUN", "--learner": "tcp://127.0.0.1:5555"}


class _Built(Exception):
    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__(parser.prog)
        self.parser = parser


def _parsers() -> list[argparse.ArgumentParser]:
    """Each command's parser, as its main builds it: main runs until it parses, and stops there."""
    from higher_dist.bench import COMMANDS

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    found, real = [], argparse.ArgumentParser.parse_known_args

    def built(self, *args, **kwargs):
        raise _Built(self)

    argparse.ArgumentParser.parse_known_args = built
    try:
        for name, target in scripts.items():
            module, function = target.split(":")
            main = getattr(importlib.import_module(module), function)
            for argv in ([[c] for c in COMMANDS] if name == "higher-bench" else [ARGV.get(name, [])]):
                with pytest.raises(_Built) as caught:
                    main(argv)
                found.append(caught.value.parser)
    finally:
        argparse.ArgumentParser.parse_known_args = real
    return found


PARSERS = _parsers()


def _stated(parser: argparse.ArgumentParser) -> list[tuple[argparse.Action, str]]:
    formatter = parser._get_formatter()
    out = []
    for action in parser._actions:
        if action.help in (None, argparse.SUPPRESS):
            continue
        text = formatter._expand_help(action)
        assert not re.search(r"\(default(?!: )", text), f"{parser.prog} {action.dest}: write '(default: X)': {text}"
        out += [(action, match) for match in STATED.findall(text)]
    return out


def _resolved(parser: argparse.ArgumentParser) -> Config | None:
    """The config a run command makes when no config flag is given."""
    flags = {a.dest for a in parser._actions}
    if not {"preset", "print_config"} <= flags:  # the commands of add_config_flags
        return None
    argv = [x for a in parser._actions if a.required for x in (a.option_strings[0], REQUIRED[a.option_strings[0]])]
    return config_from_args(parser.parse_args(argv))


def _used() -> dict[tuple[str, str], object]:
    """(command or '*', dest) -> the value the code falls back to where the argparse default is None."""
    from higher_dist.launch.topology import DEFAULT_BASE_PORT
    from higher_dist.reproduce import plan
    from higher_dist.roles.relabeler import DEFAULT_STATE_DIR

    return {("*", "port_base"): DEFAULT_BASE_PORT, ("higher-relabeler", "state_dir"): DEFAULT_STATE_DIR,
            ("higher-reproduce", "parallel"): plan.default_parallel(),
            ("higher-reproduce", "frames"): make_config("higher", "paper").frames,
            ("higher-reproduce", "experiments"): "all"}


# Defaults that are no single value, each with the check of the code that it describes.
DESCRIBED = {
    ("higher-cluster", "actors"): "the layout for this host",  # cluster_main: default_actors(available_cores())
    ("*", "threads"): "every core the other roles leave",  # torch_threads 0: launch/layout.py decides
    ("higher-cluster", "run_dir"): "runs/PRESET-WORLD-sSEED-TIME",
    ("*", "key"): "the pair named after the role, else 'client', else the folder's only pair",
    ("higher-relabeler", "advertise"): "the learner's host, base+4",
    ("higher-actor", "actor_id"): "the learner assigns one",
    ("higher-keys", "client"): "one 'client' pair",
    ("higher-reproduce", "actors"): "the layout for the cores each run gets",
    ("higher-bench soak", "warmup_minutes"): "a third of the run, at most 10",
    ("higher-bench soak", "run_dir"): "a temp folder",
    ("higher-bench checkpoint", "capacity"): "the paper world's",
    ("higher-bench checkpoint", "dir"): "a temp folder",
    ("higher-bench gpu", "actors"): "the layout's",
}


def _lookup(table: dict, prog: str, dest: str):
    return table.get((prog, dest), table.get(("*", dest)))


def _says(stated: str, value: object) -> bool:
    """Whether `stated` names `value`: the whole of it, or as a word of it (a number as written or with
    thousands separators dropped)."""
    first = stated.split(";")[0].strip()
    if isinstance(value, bool):
        return first == ("on" if value else "off")
    if isinstance(value, (int, float)):
        numbers = [float(n.replace(",", "")) for n in re.findall(r"(?<![\w.])\d[\d,]*(?:\.\d+)?(?![\w])", stated)]
        return float(value) in numbers
    text = str(value)
    return first == text or re.search(rf"(?<![\w/.-]){re.escape(text)}(?![\w/.-])", stated) is not None


def test_every_command_and_subcommand_has_a_parser_to_check():
    progs = {p.prog for p in PARSERS}
    assert {"higher-cluster", "higher-learner", "higher-relabeler", "higher-reproduce", "higher-bench soak",
            "higher-bench time-to-success"} <= progs
    assert sum(len(_stated(p)) for p in PARSERS) > 40


@pytest.mark.parametrize("parser", PARSERS, ids=lambda p: p.prog)
def test_each_stated_default_is_the_one_the_code_uses(parser):
    cfg = _resolved(parser)
    config_fields = {"preset": "preset", "world": "world.name", "profile": "profile", "frames": "frames",
                     "envs_per_actor": "envs_per_actor", "seed": "seed", "device": "device", "actors": "actors"}
    wrong = []
    for action, stated in _stated(parser):
        where = f"{parser.prog} {'/'.join(action.option_strings) or action.dest}: stated {stated!r}"
        if action.default is not None:
            if not _says(stated, action.default):
                wrong.append(f"{where}, argparse default {action.default!r}")
            continue
        phrase = _lookup(DESCRIBED, parser.prog, action.dest)
        if phrase is not None:
            if phrase not in stated:
                wrong.append(f"{where}, expected it to say {phrase!r}")
            continue
        if cfg is not None and action.dest in config_fields:
            value = cfg
            for name in config_fields[action.dest].split("."):
                value = getattr(value, name)
        else:
            value = _lookup(_used(), parser.prog, action.dest)
            assert value is not None, f"{where}: add what the code uses when it is not given to USED or DESCRIBED"
        if not _says(stated, value):
            wrong.append(f"{where}, the code uses {value!r}")
    assert not wrong, "\n".join(wrong)


def test_the_described_defaults_are_what_the_code_does(tmp_path):
    """The checks behind DESCRIBED's phrases that a unit test can make."""
    import inspect

    from higher_dist import cli
    from higher_dist.launch.layout import learner_alone
    from higher_dist.wire.allowlist import client_key_name
    from higher_dist.wire.security import generate_keys

    assert Config().torch_threads == 0 and learner_alone(8, "cpu", 0) == 6  # the relabeler's and an actor's kept
    assert "default_actors(available_cores()" in inspect.getsource(cli.cluster_main)
    assert 'runs/{cfg.preset}-{cfg.world.name}-s{cfg.seed}-' in inspect.getsource(cli.cluster_main)
    generate_keys(tmp_path / "k", clients=("relabeler", "client", "other"))
    generate_keys(tmp_path / "c", clients=("client", "other"))
    generate_keys(tmp_path / "o", clients=("other",))
    assert [client_key_name(tmp_path / d, "relabeler") for d in ("k", "c", "o")] == ["relabeler", "client", "other"]
    assert cli.keys_main([str(tmp_path / "shared")]) == 0 and (tmp_path / "shared" / "client.key_secret").is_file()
