"""deploy/systemd: the units' own ExecStart lines, run as systemd would run them (the shipped environment
file with this machine's values, StateDirectory as $STATE_DIRECTORY, %i substituted), on loopback with keys.

The first start makes a run and finishes it; a second start of the learner resumes it; an actor whose
number is outside the learner's --actors is refused with exit code 2, which the units do not restart.
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))
from hd_harness import FAST_SETTINGS, Proc, RunWatch  # noqa: E402

from higher_dist.launch.topology import free_base_port  # noqa: E402
from higher_dist.wire.security import generate_keys  # noqa: E402

UNITS = Path(__file__).resolve().parents[2] / "deploy" / "systemd"
FRAMES = 1500


def unit(name: str) -> dict[str, list[str]]:
    """key -> values of a unit file, continuation lines joined as systemd joins them."""
    text = re.sub(r"\\\n", " ", (UNITS / name).read_text())
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def env_file() -> dict[str, str]:
    pairs = (line.split("=", 1) for line in (UNITS / "higher.env").read_text().splitlines()
             if "=" in line and not line.startswith("#"))
    return {k: v for k, v in pairs}


def exec_argv(name: str, instance: str = "") -> list[str]:
    return shlex.split(unit(name)["ExecStart"][0].replace("%i", instance))


def test_units_are_complete():
    shipped = env_file()
    for name in ("higher-learner.service", "higher-relabeler.service", "higher-actor@.service"):
        u = unit(name)
        assert u["Wants"] == ["network-online.target"] and "network-online.target" in u["After"][0], name
        assert u["User"] == ["higher"] and u["EnvironmentFile"] == ["/etc/higher/higher.env"], name
        assert u["RestartPreventExitStatus"] == ["2"], name
        script = exec_argv(name, "0")[2]
        assert "--keys" in script, name
        used = set(re.findall(r"\$\{?([A-Z_]+)", script)) - {"STATE_DIRECTORY"}
        assert used <= set(shipped), f"{name} uses {sorted(used - set(shipped))}, not in higher.env"
        if name != "higher-actor@.service":
            assert u["StateDirectory"], name
    assert "--actors" in exec_argv("higher-learner.service")[2]
    assert "--advertise" in exec_argv("higher-relabeler.service")[2]



HARDENING = {"NoNewPrivileges": "yes", "ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes",
             "RestrictSUIDSGID": "yes", "CapabilityBoundingSet": "", "UMask": "0077"}


def test_units_are_hardened_and_verified_by_systemd(tmp_path):
    for name in ("higher-learner.service", "higher-relabeler.service", "higher-actor@.service"):
        u = unit(name)
        for key, value in HARDENING.items():
            assert u.get(key) == [value], (name, key, u.get(key))
    if not shutil.which("systemd-analyze"):
        pytest.skip("systemd-analyze is not installed on this machine (apt-get install systemd)")
    # verify warns about unknown keys and bad values but still exits 0: any line about our units fails.
    copies = []
    for name in ("higher-learner.service", "higher-relabeler.service", "higher-actor@.service"):
        copies.append(tmp_path / name)
        copies[-1].write_text((UNITS / name).read_text())
    done = subprocess.run(["systemd-analyze", "verify", "--man=no", *map(str, copies)], capture_output=True,
                          text=True, cwd=tmp_path)
    complaints = [line for line in (done.stdout + done.stderr).splitlines() if str(tmp_path) in line]
    assert done.returncode == 0 and not complaints, done.stdout + done.stderr
    broken = tmp_path / "broken.service"
    broken.write_text((UNITS / "higher-learner.service").read_text().replace("NoNewPrivileges", "NoNewPrivilege"))
    done = subprocess.run(["systemd-analyze", "verify", "--man=no", str(broken)], capture_output=True, text=True,
                          cwd=tmp_path)
    assert "NoNewPrivilege" in done.stdout + done.stderr  # the check above can fail


def test_units_start_resume_and_refuse(tmp_path):
    keys = tmp_path / "keys"
    generate_keys(keys)
    port = free_base_port()
    flags = " ".join(f"--set {k}={'[' + ','.join(map(str, v)) + ']' if isinstance(v, list) else v}"
                     for k, v in FAST_SETTINGS.items() if v is not None)
    env = dict(os.environ, **env_file())
    env.update(VENV=str(Path(sys.executable).parent.parent), HEAD="127.0.0.1", RELABELER_HOST="127.0.0.1",
               PORT_BASE=str(port), KEYS=str(keys), WORLD="small", ACTORS="1",
               LEARNER_FLAGS=f"--frames {FRAMES} --envs-per-actor 8 {flags}")
    state = {name: tmp_path / "state" / name for name in ("learner", "relabeler")}
    for d in state.values():
        d.mkdir(parents=True)

    def start(name: str, instance: str = "", state_dir: Path | None = None) -> Proc:
        unit_env = dict(env, **({"STATE_DIRECTORY": str(state_dir)} if state_dir else {}))
        return Proc(exec_argv(name, instance), tmp_path / f"{name}{instance}.out", tmp_path, env=unit_env)

    learner = start("higher-learner.service", state_dir=state["learner"])
    watch = RunWatch(state["learner"], [learner])
    try:
        watch.add(start("higher-relabeler.service", state_dir=state["relabeler"]))
        actor = watch.add(start("higher-actor@.service", "0"))
        assert learner.wait(240) == 0, watch.diagnostics()
        assert watch.records()[-1]["frames"] >= FRAMES
        assert actor.wait(30) == 0 and "resumed at" not in learner.output()  # the first start makes the run
        # A second start, as after a reboot: the same ExecStart resumes the run it made, finds it over and
        # leaves it as it ended (no second final evaluation, record or checkpoint).
        records, ckpt = len(watch.records()), (state["learner"] / "learner.ckpt").stat().st_mtime_ns
        again = watch.add(start("higher-learner.service", state_dir=state["learner"]))
        assert again.wait(120) == 0, watch.diagnostics()
        assert "resumed at" in again.output() and "already reached its budget" in again.output()
        assert len(watch.records()) == records
        assert (state["learner"] / "learner.ckpt").stat().st_mtime_ns == ckpt
        # Actor 1 with ACTORS=1: refused by a running learner, exit 2, which RestartPreventExitStatus keeps down.
        env.update(LEARNER_FLAGS=f"--frames {FRAMES * 100} --envs-per-actor 8 {flags}")
        third = watch.add(start("higher-learner.service", state_dir=state["learner"]))
        outsider = watch.add(start("higher-actor@.service", "1"))
        assert outsider.wait(120) == 2, outsider.output()
        assert "actor number 1 is outside this run's 1 actor(s)" in outsider.output()
        third.stop()
    finally:
        watch.cleanup()
