"""One set of CLI rules: a path or address problem is a one-line refusal with exit code 2 (never a
traceback), counts are parsed the same way by every command (2000000, 2_000_000, 2e6) and negative ones
are refused, and `make reproduce` refuses a NAME=VALUE word that make would otherwise swallow."""
from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

from higher_dist import cli
from higher_dist.launch.topology import free_base_port

REPO = Path(__file__).resolve().parents[2]


def call(main, *args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:
            code = e.code
    return code, out.getvalue(), err.getvalue()


def test_a_run_dir_that_is_a_file_is_refused_in_one_line(tmp_path):
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    for main, extra in ((cli.cluster_main, ["--no-dashboard", "--port-base", free_base_port()]), (cli.run_main, [])):
        code, _, err = call(main, "--world", "small", "--run-dir", a_file, *extra)
        assert code == 2 and "is a file, not a folder" in err and "Traceback" not in err, err
    assert a_file.read_text() == "mine"


def test_keys_and_plot_outputs_that_are_files_are_refused(tmp_path):
    a_file = tmp_path / "f"
    a_file.write_text("x")
    code, _, err = call(cli.keys_main, a_file)
    assert code == 2 and "is a file" in err
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.jsonl").write_text(json.dumps({"time": 1.0, "frames": 10, "preset": "her"}) + "\n")
    (run / "config.json").write_text("{}")
    code, _, err = call(cli.plot_main, run, "--out", a_file)
    assert code == 2 and "--out" in err and "is a file" in err, err


def test_an_address_this_host_does_not_have_is_named_as_such(tmp_path):
    # 192.0.2.1 is TEST-NET-1 (RFC 5737): never an address of a real host.
    code, _, err = call(cli.cluster_main, "--world", "small", "--no-dashboard", "--insecure", "--host", "192.0.2.1",
                        "--port-base", free_base_port(), "--run-dir", tmp_path / "run")
    assert code == 2 and "192.0.2.1 is not an address of this host" in err and "in use" not in err, err


@pytest.mark.parametrize("main, flags", [(cli.cluster_main, ["--max-restarts", "-3"]),
                                         (cli.actor_main, ["--learner", "tcp://127.0.0.1:5555", "--actor-id", "-1"]),
                                         (cli.cluster_main, ["--frames", "-5"]),
                                         (cli.cluster_main, ["--frames", "1.5e3x"]),
                                         (cli.cluster_main, ["--frames", "2.5"])])
def test_negative_or_broken_counts_are_refused(main, flags):
    code, _, err = call(main, *flags)
    assert code == 2 and flags[-2] in err, err


@pytest.mark.parametrize("text", ["1000000", "1_000_000", "1e6", "1E6"])
def test_every_command_reads_a_count_the_same_way(text):
    code, out, err = call(cli.cluster_main, "--world", "small", "--frames", text, "--print-config")
    assert code == 0, err
    assert json.loads(out)["frames"] == 1_000_000


def test_make_reproduce_refuses_a_word_make_would_swallow():
    if shutil.which("make") is None:
        pytest.skip("make is not installed on this machine")
    p = subprocess.run(["make", "-n", "reproduce", "--", "main", "--seeds=2"], cwd=REPO, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode != 0 and "--seeds=2" in p.stderr and "--seeds 2" in p.stderr, p.stderr
    ok = subprocess.run(["make", "-n", "reproduce", "--", "main", "--seeds", "2"], cwd=REPO, capture_output=True,
                        text=True, timeout=60)
    assert ok.returncode == 0 and "--seeds 2" in ok.stdout, ok.stdout + ok.stderr


def test_keys_folders_are_private_whatever_the_umask(tmp_path):
    old = os.umask(0)
    try:
        code, _, err = call(cli.keys_main, tmp_path / "keys")
    finally:
        os.umask(old)
    assert code == 0, err
    for folder in (tmp_path / "keys", tmp_path / "keys" / "allowed_clients"):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700, folder


def test_every_entry_point_shows_its_defaults_in_help():
    for main, shown in ((cli.cluster_main, ["(default: higher)", "(default: 0)", "(default: auto)", "(default: 5)"]),
                        (cli.learner_main, ["(default: higher)", "(default: paper)"]),
                        (cli.run_main, ["(default: higher)", "(default: 10000)"]),
                        (cli.render_main, ["(default:"]), (cli.plot_main, ["(default:"])):
        code, out, _ = call(main, "--help")
        assert code == 0
        flat = " ".join(out.split())
        assert all(text in flat for text in shown), (main.__name__, [t for t in shown if t not in flat])
