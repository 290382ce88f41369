"""deploy/systemd under a real systemd: PID 1 of new PID, mount, network, UTS, IPC and cgroup namespaces.

test_systemd_units.py runs the units' ExecStart lines as systemd would; this one lets systemd 252 itself
run the shipped unit files (User=higher, StateDirectory=, the hardening) on a tiny run on loopback, and
checks that every unit reaches active, the learner finishes its budget and exits 0, nothing is restarted
after it, and the sandbox is really in effect in the roles' processes (/proc/PID/status, mountinfo).

The host is never touched: systemd boots on an overlay of / whose writes go to a tmpfs (so `useradd
higher`, /etc/systemd/system, /var/lib/higher, the journal live and die with the namespace), with a private
/dev and a read-only /proc/sys (its sysctl and static-node services would otherwise write the host's kernel
settings and /dev), its own loopback network and a cgroup subtree that is removed at the end.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))
from hd_harness import FAST_SETTINGS  # noqa: E402

from higher_dist.rundir import read_metrics  # noqa: E402
from higher_dist.wire.security import generate_keys  # noqa: E402

UNITS = Path(__file__).resolve().parents[2] / "deploy" / "systemd"
NAMES = ("higher-learner.service", "higher-relabeler.service", "higher-actor@.service")
ROLES = ("higher-learner", "higher-relabeler", "higher-actor@0", "higher-actor@1")
FRAMES = 1500
CG_V1 = Path("/sys/fs/cgroup/systemd")  # the name=systemd hierarchy of a hybrid (v1) host
CG_V2 = Path("/sys/fs/cgroup/unified")

# Runs as PID 1 of the new namespaces, then becomes systemd. $1: an empty folder for the tmpfs, $2: the
# files to lay over / (units, env file, keys, masks). Every mount is private to the new mount namespace.
BOOT = r"""set -eu
T=$1; STAGE=$2; R=$T/root
mount -t tmpfs -o mode=755 hdsd "$T"
mkdir "$T/upper" "$T/work" "$R"
mount -t overlay overlay -o "lowerdir=/,upperdir=$T/upper,workdir=$T/work" "$R"
[ "$(findmnt -n -o FSTYPE "$R")" = overlay ]  # never write below unless it is the overlay
mount -t proc proc "$R/proc"
mount --bind "$R/proc/sys" "$R/proc/sys"; mount -o remount,bind,ro "$R/proc/sys"
mount -t sysfs -o ro sysfs "$R/sys"
mount -t tmpfs -o mode=755 cgroup "$R/sys/fs/cgroup"
mkdir "$R/sys/fs/cgroup/systemd" "$R/sys/fs/cgroup/unified"
mount -t cgroup -o none,name=systemd cgroup "$R/sys/fs/cgroup/systemd"
mount -t cgroup2 cgroup2 "$R/sys/fs/cgroup/unified"
mount -t tmpfs -o mode=755 dev "$R/dev"
for n in null zero full random urandom tty; do touch "$R/dev/$n"; mount --bind "/dev/$n" "$R/dev/$n"; done
mkdir "$R/dev/pts" "$R/dev/shm"
mount -t devpts -o newinstance,ptmxmode=0666 devpts "$R/dev/pts"; ln -s pts/ptmx "$R/dev/ptmx"
mount -t tmpfs -o mode=1777 shm "$R/dev/shm"
mount -t tmpfs -o mode=1777 tmp "$R/tmp"
mount -t tmpfs -o mode=755 run "$R/run"
cp -a "$STAGE/." "$R/"
chroot "$R" sh -c 'id higher >/dev/null 2>&1 || useradd --system --no-create-home --user-group higher'
chroot "$R" chown -R higher:higher /etc/higher/keys
cd "$R"; mkdir oldroot; pivot_root . oldroot; umount -l /oldroot; rmdir /oldroot
exec env container=other /lib/systemd/systemd --system --unit=higher-test.target --log-target=journal
"""


def ok(*argv: str) -> bool:
    return subprocess.run(argv, capture_output=True).returncode == 0


def preflight(tmp_path: Path) -> None:
    """Skip, naming what is missing, where this machine cannot boot systemd in namespaces."""
    if os.geteuid() != 0:
        pytest.skip("needs root (CAP_SYS_ADMIN) to make namespaces, mounts and cgroups for a systemd")
    for tool in ("unshare", "nsenter", "findmnt", "useradd"):
        if not shutil.which(tool):
            pytest.skip(f"{tool} is not installed")
    if not os.access("/lib/systemd/systemd", os.X_OK):
        pytest.skip("/lib/systemd/systemd is not installed (apt-get install systemd)")
    if not (CG_V1 / "cgroup.procs").exists() or not (CG_V2 / "cgroup.procs").exists():
        pytest.skip("no hybrid cgroup layout (/sys/fs/cgroup/systemd name=systemd + /sys/fs/cgroup/unified): "
                    "only that layout is set up here")
    probe = tmp_path / "probe"
    probe.mkdir()
    if not ok("unshare", "--pid", "--fork", "--mount", "--net", "--uts", "--ipc", "--cgroup",
              "--propagation", "private", "sh", "-c",
              f"mount -t tmpfs t {probe} && mkdir {probe}/u {probe}/w {probe}/r && mount -t overlay o "
              f"-o lowerdir=/,upperdir={probe}/u,workdir={probe}/w {probe}/r"):
        pytest.skip("cannot make PID/mount/net/cgroup namespaces or an overlay of / (no CAP_SYS_ADMIN, or "
                    "a seccomp profile that forbids unshare/mount)")


def stage_files(stage: Path) -> None:
    """/etc of the booted systemd: the shipped units, higher.env with this machine's values, keys, masks."""
    system = stage / "etc" / "systemd" / "system"
    system.mkdir(parents=True)
    (system / "higher-test.target").write_text("[Unit]\nDescription=default target of the test's systemd\n")
    # The units' DefaultDependencies pull sysinit.target; mask its services (kernel modules, binfmt, clock,
    # random seed...), all host-level work. journald stays: `journalctl -u` is how a failure is read.
    for wants in (Path("/lib/systemd/system/sysinit.target.wants"), Path("/etc/systemd/system/sysinit.target.wants"),
                  Path("/lib/systemd/system/timers.target.wants")):
        for name in (os.listdir(wants) if wants.is_dir() else []):
            if not name.startswith("systemd-journal") and name.endswith((".service", ".mount", ".automount",
                                                                          ".path", ".timer")):
                (system / name).symlink_to("/dev/null")
    for name in NAMES:
        shutil.copy(UNITS / name, system / name)
        # This machine's interpreter may live under /root (pyenv): ProtectHome=yes would hide it. The
        # drop-in keeps home directories empty (tmpfs) and binds only the interpreter, read-only, back.
        homes = [p for p in {Path(sys.base_prefix).resolve(), Path(sys.prefix).resolve()}
                 if str(p).startswith(("/root", "/home", "/run/user"))]
        if homes:
            (system / f"{name}.d").mkdir()
            (system / f"{name}.d" / "test.conf").write_text(
                "[Service]\nProtectHome=tmpfs\n" + "".join(f"BindReadOnlyPaths={p}\n" for p in homes))
    flags = " ".join(f"--set {k}={'[' + ','.join(map(str, v)) + ']' if isinstance(v, list) else v}"
                     for k, v in FAST_SETTINGS.items() if v is not None)
    values = {"VENV": str(Path(sys.prefix)), "HEAD": "127.0.0.1", "RELABELER_HOST": "127.0.0.1",
              "WORLD": "small", "ACTORS": "2", "LEARNER_FLAGS": f"--frames {FRAMES} --envs-per-actor 8 {flags}"}
    env = []
    for line in (UNITS / "higher.env").read_text().splitlines():
        key = line.split("=", 1)[0]
        env.append(f"{key}={values[key]}" if "=" in line and key in values else line)
    (stage / "etc" / "higher").mkdir(parents=True)
    (stage / "etc" / "higher" / "higher.env").write_text("\n".join(env) + "\n")
    generate_keys(stage / "etc" / "higher" / "keys")  # chowned to `higher` inside, once the user exists


class Booted:
    """systemd as PID 1 of new namespaces; `ctl` runs systemctl (or any command) inside them."""

    def __init__(self, tmp_path: Path) -> None:
        self.cgroup = f"hdsd-test-{os.getpid()}"
        self.log = open(tmp_path / "boot.log", "w")
        (tmp_path / "T").mkdir()
        # The outer sh moves itself into a fresh cgroup subtree first, so --cgroup makes that subtree the
        # namespace's root: systemd creates its slices there, not in the host's hierarchy.
        outer = ('set -e; for h in "$1" "$2"; do mkdir "$h/$3"; echo $$ > "$h/$3/cgroup.procs"; done; '
                 'exec unshare --pid --fork --mount --net --uts --ipc --cgroup --propagation private sh -c "$6" boot "$4" "$5"')
        self.proc = subprocess.Popen(["sh", "-c", outer, "outer", str(CG_V1), str(CG_V2), self.cgroup,
                                      str(tmp_path / "T"), str(tmp_path / "stage"), BOOT],
                                     stdout=self.log, stderr=subprocess.STDOUT)
        self.pid1 = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and self.proc.poll() is None:
            kids = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children")
            pids = kids.read_text().split() if kids.exists() else []
            if pids and "systemd" in Path(f"/proc/{pids[0]}/comm").read_text():
                self.pid1 = int(pids[0])
                if self.run("systemctl", "is-system-running").stdout.strip() in ("running", "degraded"):
                    return
            time.sleep(0.5)
        self.close()
        raise AssertionError(f"systemd did not boot: {(tmp_path / 'boot.log').read_text()}")

    def run(self, *argv: str) -> subprocess.CompletedProcess:
        return subprocess.run(["nsenter", "-t", str(self.pid1), "-m", "-p", "-n", "-u", "-i", *argv],
                              capture_output=True, text=True, timeout=60)

    def show(self, unit: str, *props: str) -> dict[str, str]:
        out = self.run("systemctl", "show", unit, "-p", ",".join(props)).stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def path(self, inside: str) -> Path:
        return Path(f"/proc/{self.pid1}/root{inside}")  # the namespace's tree, its /proc included

    def journal(self) -> str:
        return self.run("journalctl", "--no-pager", "-o", "cat", *sum((["-u", r] for r in ROLES), [])).stdout[-6000:]

    def close(self) -> None:
        # poweroff makes PID 1 stop every unit and exit; SIGKILL of PID 1 kills all of the namespace anyway.
        if self.pid1:
            self.run("systemctl", "poweroff", "--no-block")
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            if self.pid1:
                os.kill(self.pid1, 9)
            self.proc.wait(30)
        self.log.close()
        for h in (CG_V1, CG_V2):  # the subtree, deepest first (rmdir of an empty cgroup)
            for d in sorted((h / self.cgroup).rglob("*"), key=lambda p: -len(p.parts)) if (h / self.cgroup).exists() else []:
                if d.is_dir():
                    d.rmdir()
            if (h / self.cgroup).exists():
                (h / self.cgroup).rmdir()


def test_units_under_a_real_systemd(tmp_path):
    preflight(tmp_path)
    stage_files(tmp_path / "stage")
    sd = Booted(tmp_path)
    try:
        done = sd.run("systemctl", "start", *ROLES)
        assert done.returncode == 0, done.stderr + sd.journal()
        for role in ROLES:
            assert sd.show(role, "ActiveState")["ActiveState"] == "active", role + "\n" + sd.journal()
            assert sd.show(role, "NoNewPrivileges")["NoNewPrivileges"] == "yes"
        # The sandbox, read from the running processes themselves, not from the unit files.
        time.sleep(3)
        for role in ROLES:
            pid = sd.show(role, "MainPID")["MainPID"]
            status = dict(line.split(":", 1) for line in sd.path(f"/proc/{pid}/status").read_text().splitlines())
            uid = sd.run("id", "-u", "higher").stdout.strip()
            assert status["Uid"].split()[0] == uid and uid != "0", (role, status["Uid"])
            assert status["NoNewPrivs"].strip() == "1" and status["Seccomp"].strip() == "2", role
            assert int(status["CapBnd"], 16) == 0 and int(status["CapEff"], 16) == 0, role
            mounts = {}  # mount point -> (root in its filesystem, options, filesystem type)
            for f in (line.split() for line in sd.path(f"/proc/{pid}/mountinfo").read_text().splitlines()):
                mounts[f[4]] = (f[3], f[5].split(","), f[f.index("-") + 1])
            assert "ro" in mounts["/"][1], (role, mounts["/"])  # ProtectSystem=strict
            assert "/systemd-private-" in mounts["/tmp"][0], (role, mounts["/tmp"])  # PrivateTmp
            assert mounts["/root"][2] == "tmpfs" and mounts["/home"][2] == "tmpfs", role  # ProtectHome (tmpfs)
            if "actor" not in role:
                state = f"/var/lib/higher/{role.split('-')[1]}"
                assert "rw" in mounts[state][1], (role, mounts.get(state))  # StateDirectory, the one rw place
        # The learner reaches its budget and exits 0; every role then stops with 0 and nothing restarts.
        deadline = time.monotonic() + 180
        while sd.show("higher-learner", "ActiveState")["ActiveState"] in ("active", "activating", "deactivating"):
            assert time.monotonic() < deadline, "learner still running\n" + sd.journal()
            assert sd.show("higher-learner", "NRestarts")["NRestarts"] == "0", "learner restarted\n" + sd.journal()
            time.sleep(2)
        learner = sd.show("higher-learner", "Result", "ExecMainStatus", "NRestarts", "ActiveState")
        assert learner == {"Result": "success", "ExecMainStatus": "0", "NRestarts": "0",
                           "ActiveState": "inactive"}, str(learner) + sd.journal()
        records = read_metrics(sd.path("/var/lib/higher/learner/metrics.jsonl"))
        assert records and records[-1]["frames"] >= FRAMES, records[-1:]
        time.sleep(15)  # past every RestartSec (10 s at most): a restart would show now
        for role in ROLES:
            got = sd.show(role, "ActiveState", "Result", "NRestarts", "ExecMainStatus")
            assert got == {"ActiveState": "inactive", "Result": "success", "NRestarts": "0",
                           "ExecMainStatus": "0"}, f"{role}: {got}\n{sd.journal()}"
    finally:
        sd.close()
