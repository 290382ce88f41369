"""Bad flags and configs are refused by the entry points themselves: exit code 2 and a message naming the
problem, before anything starts. Each entry point runs once as a real subprocess, as a user would run it;
the variants of one entry point's checks call the same `main` function in this process (what the console
script returns is exactly its return value, or argparse's SystemExit code), which saves a Python start each.
"""
from __future__ import annotations

import contextlib
import io
import subprocess

import pytest

from hd_harness import entry
from higher_dist import cli
from higher_dist.launch.topology import free_base_port


def run(role: str, *args, cwd, timeout: float = 90.0) -> subprocess.CompletedProcess:
    return subprocess.run(entry(role, *args), cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def call(main, *args) -> tuple[int, str]:
    """(exit code, stderr) of an entry point's main called here; argparse errors exit via SystemExit."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:
            code = e.code
    return code, err.getvalue()


@pytest.mark.parametrize("flags, expected", [
    (["--preset", "nope"], ["--preset", "invalid choice", "'nope'"]),
    (["--set", "nosuch.field=1"], ["nosuch.field", "no such config field"]),
])
def test_cluster_refuses_bad_flags_as_a_process(tmp_path, flags, expected):
    run_dir = tmp_path / "run"
    p = run("cluster", *flags, "--no-dashboard", "--port-base", free_base_port(), "--run-dir", run_dir,
            cwd=tmp_path)
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert "higher-cluster: error" in p.stderr
    for text in expected:
        assert text in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert not run_dir.exists(), "a refused run must not create its run directory"


@pytest.mark.parametrize("flags, expected", [
    (["--preset", "nope"], ["--preset", "invalid choice", "'nope'"]),
    (["--world", "nope"], ["--world", "unknown world", "'nope'", "BabyAI-PickupDist-v0"]),
    (["--world", "BabyAI-GoToSeq-v0"], ["'BabyAI-GoToSeq-v0'", "not supported", "'pick up', 'go to' or 'open'",
                                        "BabyAI-GoToRedBall-v0"]),
    (["--world", "BabyAI-Nope-v0"], ["'BabyAI-Nope-v0'", "unknown id"]),
    (["--world", "BabyAI-PickupDist-v0", "--preset", "reward"], ["world.reward_shaping", "BabyAI"]),
    (["--world", "BabyAI-PickupDist-v0", "--set", "world.view_size=5"], ["world.view_size", "7x7"]),
    (["--actors", "0"], ["--actors", "positive integer", "0"]),
    (["--envs-per-actor", "-3"], ["--envs-per-actor", "positive integer"]),
    (["--world", "small", "--set", "world.n_objects=1000"], ["world.n_objects", "1000", "do not fit"]),
    (["--set", "nosuch.field=1"], ["nosuch.field", "no such config field"]),
    (["--set", "dqn.lr=fast"], ["dqn.lr", "expected a number"]),
    (["--set", "exploration.repeat_max=0"], ["exploration.repeat_max", "must be >= 1"]),
    (["--set", "dqn.average_tau=-0.1"], ["dqn.average_tau", "must be in [0, 1]"]),
    (["--set", "dqn.lr_end_fraction=0"], ["dqn.lr_end_fraction", "must be in (0, 1]"]),
    (["--set", "generator.lr_end_fraction=1.5"], ["generator.lr_end_fraction", "must be in (0, 1]"]),
    (["--set", "generator.lr_decay_updates=-1"], ["generator.lr_decay_updates", "must be >= 0"]),
    (["--set", "frames"], ["--set", "FIELD=VALUE"]),
])
def test_cluster_refuses_bad_flags_and_configs(tmp_path, flags, expected):
    run_dir = tmp_path / "run"
    code, err = call(cli.cluster_main, *flags, "--no-dashboard", "--port-base", free_base_port(),
                     "--run-dir", run_dir)
    assert code == 2, (code, err)
    assert "higher-cluster" in err and "error" in err
    for text in expected:
        assert text in err, err
    assert not run_dir.exists(), "a refused run must not create its run directory"


def test_cluster_refuses_to_overwrite_a_run_without_resume(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "learner.ckpt").write_bytes(b"a previous run")
    code, err = call(cli.cluster_main, "--world", "small", "--no-dashboard", "--port-base", free_base_port(),
                     "--run-dir", run_dir)
    assert code == 2, (code, err)
    assert "--resume" in err and str(run_dir) in err
    assert (run_dir / "learner.ckpt").read_bytes() == b"a previous run"
    assert not (run_dir / "logs").exists()


@pytest.mark.parametrize("address", ["garbage", "127.0.0.1:5555"])
def test_actor_refuses_a_malformed_learner_address(tmp_path, address):
    p = run("actor", "--learner", address, cwd=tmp_path)
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert "higher-actor: error" in p.stderr
    assert repr(address) in p.stderr
    assert "tcp://HOST:PORT" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr


def test_learner_resume_without_a_checkpoint_is_refused(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    p = run("learner", "--world", "small", "--resume", "--run-dir", empty, "--port-base", free_base_port(),
            cwd=tmp_path)
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert "higher-learner: error" in p.stderr and "--resume" in p.stderr and str(empty) in p.stderr
    assert "no learner checkpoint" in p.stderr or "config.json does not exist" in p.stderr
    assert "Traceback" not in p.stderr
    assert not (empty / "learner.ckpt").exists() and not (empty / "config.json").exists()


def test_learner_resume_of_a_checkpoint_of_other_shapes_is_refused(tmp_path):
    """A learner.ckpt whose network has other shapes (another version's) is refused by name, no traceback."""
    import torch

    from higher_dist.config_presets import make_config
    from higher_dist.learning.agent import AgentBuilder
    from higher_dist.rundir import RunDir

    rd = RunDir(tmp_path / "run")
    rd.write_config(make_config("dqn", "small"))
    other = AgentBuilder(make_config("dqn", "small", **{"network.hidden": 32})).learner()
    rd.save_checkpoint("learner", {"core": other.state_dict(with_replay=False), "weights_version": 0,
                                   "torch_rng": torch.get_rng_state(), "elapsed_s": 0.0})
    p = run("learner", "--resume", "--run-dir", rd.path, "--port-base", free_base_port(), cwd=tmp_path)
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert "higher-learner: error: --resume" in p.stderr and "learner.ckpt does not fit this version's network" in p.stderr
    assert "Traceback" not in p.stderr


def test_plot_of_an_empty_directory_is_refused(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    p = run("plot", empty, "--out", tmp_path / "figures", cwd=tmp_path)
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert str(empty) in p.stderr and "no run" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert not list(tmp_path.rglob("*.png")), "no figure for a directory without a run"


def test_cluster_refuses_ports_already_in_use(tmp_path, capsys):
    import socket as pysocket

    from higher_dist.cli import cluster_main
    from higher_dist.launch.topology import free_base_port

    base = free_base_port()
    held = pysocket.socket()
    # Listening with SO_REUSEADDR: a bind that a TIME_WAIT left by an earlier run on this port would
    # refuse goes through, and the listener still keeps every later bind off the port.
    held.setsockopt(pysocket.SOL_SOCKET, pysocket.SO_REUSEADDR, 1)
    held.bind(("127.0.0.1", base + 2))  # the weights port
    held.listen()
    try:
        rc = cluster_main(["--world", "small", "--no-dashboard", "--run-dir", str(tmp_path / "run"),
                           "--port-base", str(base)])
    finally:
        held.close()
    assert rc == 2
    err = capsys.readouterr().err
    assert f"weights port {base + 2}" in err and "--port-base" in err, err
    assert not (tmp_path / "run" / "logs").exists()  # nothing was started


def test_cluster_refuses_ports_another_launcher_is_claiming(tmp_path, capsys):
    """Two launchers started at once on one port range both find the ports free (no learner has bound
    them yet): the port claims make the second one refuse, by name, before it starts anything."""
    from higher_dist.cli import cluster_main
    from higher_dist.launch.topology import Endpoints, claim_ports, free_base_port

    base = free_base_port()
    claims = claim_ports(Endpoints.from_base("127.0.0.1", base))  # what a starting launcher holds
    try:
        rc = cluster_main(["--world", "small", "--no-dashboard", "--run-dir", str(tmp_path / "run"),
                           "--port-base", str(base)])
        assert rc == 2
        err = capsys.readouterr().err
        assert f"port {base}" in err and "another higher-cluster" in err and "--port-base" in err, err
        assert not (tmp_path / "run" / "logs").exists()  # nothing was started
        # An overlapping range is refused too; the claims are per port.
        try:
            claim_ports(Endpoints.from_base("127.0.0.1", base + 1))
        except ValueError as e:
            assert f"port {base + 1}" in str(e)
        else:
            raise AssertionError("an overlapping port range was claimed twice")
    finally:
        for claim in claims:
            claim.close()
    # Once the first launcher lets go (it exits), the range can be claimed again.
    for claim in claim_ports(Endpoints.from_base("127.0.0.1", base + 1)):
        claim.close()
