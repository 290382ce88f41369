"""How one host's cores are shared between the roles of a run: the one place that decides it.

The learner's updates bound the run's frame rate (frames/s = learner samples/s / samples per insert),
so every core the actors and the relabeler leave idle goes to the learner as torch threads. An actor
(one batched world and one small forward pass per step) and the relabeler (a generator update now and
then) each keep one thread. The actors needed are few: one actor with 32 environments makes more
frames than a CPU learner consumes, so on a CPU host the actors grow slowly with the cores and the
learner takes the rest; on a GPU host the learner needs a core or two to feed the device and the
actors take the others (docs/benchmarks.md, "Layout per core count", has the measurements).

`torch_threads` in the config overrides the learner's share (0, the default, lets the layout decide).
"""
from __future__ import annotations

import os
import platform
from dataclasses import asdict, dataclass
from pathlib import Path

MAX_AUTO_ACTORS = 16


def available_cores() -> int:
    """Cores this process may run on: its CPU affinity (what taskset, Slurm and cpusets grant), further
    capped by a cgroup v2 CPU quota (`cpu.max`, as a container runtime or systemd sets it)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    quota = _cgroup_quota()
    return max(1, min(cores, quota) if quota else cores)


def _cgroup_quota() -> int | None:
    try:
        text = Path("/sys/fs/cgroup/cpu.max").read_text().split()
    except OSError:
        return None
    if len(text) != 2 or text[0] == "max":
        return None
    try:
        return max(1, int(int(text[0]) / int(text[1])))
    except (ValueError, ZeroDivisionError):
        return None


def machine() -> str:
    """Cores, CPU model and vector extensions, memory, accelerator and versions: what a reader needs to
    compare figures (the benchmarks and higher-reproduce record it)."""
    import torch  # the learner's library; its version and device are part of the result

    model, flags = "", []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = line.split(":", 1)[1].split()
    except OSError:
        pass
    # The extensions torch's CPU kernels pick between: figures differ across them.
    simd = sorted(f for f in flags if f in ("avx2", "fma") or f.startswith(("avx512", "amx")))
    cpu = (model or platform.machine()) + (f"; {' '.join(simd)}" if simd else "; no avx2" if flags else "")
    try:
        memory = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2 ** 30:.0f} GiB"
    except (ValueError, OSError, AttributeError):
        memory = ""
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return (f"{os.cpu_count()} cores ({cpu}){memory}, {gpu}, Python {platform.python_version()}, "
            f"torch {torch.__version__}")


def is_gpu(device: str) -> bool:
    return device.startswith("cuda")


@dataclass(frozen=True)
class Layout:
    cores: int
    actors: int
    learner_threads: int
    actor_threads: int
    relabeler_threads: int
    learner_device: str

    def describe(self) -> str:
        """One line for the dashboard, the launcher's log and the run's metrics."""
        actors = f"{self.actors} actor{'s' if self.actors != 1 else ''} x {self.actor_threads} thread"
        return (f"{self.cores} cores: learner {self.learner_threads} thread{'s' if self.learner_threads != 1 else ''}"
                f" on {self.learner_device}, relabeler {self.relabeler_threads}, {actors}")

    def to_dict(self) -> dict:
        return asdict(self)


def default_actors(cores: int, learner_device: str = "cpu") -> int:
    """Actors that keep the learner fed, leaving it the rest of the cores.

    CPU learner: one actor per 8 cores, at least 1 (2 cores: 1, 8: 1, 16: 2). GPU learner: every core
    but the learner's two and the relabeler's one, at least 1, at most MAX_AUTO_ACTORS."""
    if is_gpu(learner_device):
        return max(1, min(MAX_AUTO_ACTORS, cores - 3))
    return max(1, min(MAX_AUTO_ACTORS, cores // 8))


def plan_layout(cores: int, actors: int | None = None, learner_device: str = "cpu",
                learner_threads: int = 0) -> Layout:
    """The layout of one host running every role. `actors` None: `default_actors`. `learner_threads` > 0
    forces the learner's share (the config's torch_threads); 0 gives it every core the others leave."""
    if cores < 1:
        raise ValueError(f"cores: must be >= 1, got {cores}")
    if actors is None:
        actors = default_actors(cores, learner_device)
    if actors < 1:
        raise ValueError(f"actors: must be >= 1, got {actors}")
    if learner_threads > 0:
        threads = learner_threads
    elif is_gpu(learner_device):
        threads = min(2, cores)  # enough to feed the device; the kernels run on the GPU
    else:
        threads = max(1, cores - actors - 1)
    return Layout(cores=cores, actors=actors, learner_threads=threads, actor_threads=1, relabeler_threads=1,
                  learner_device=learner_device)


def learner_alone(cores: int, learner_device: str = "cpu", learner_threads: int = 0) -> int:
    """torch threads of a learner started on its own (`higher-learner`, by Slurm or systemd): the config's
    torch_threads when set (the sbatch script sets it from its allocation), else two for a GPU learner,
    else the host's cores but two, which the relabeler and an actor on the same host keep. Never more:
    an OpenMP thread that waits for a core another process holds spins, and a learner with more threads
    than free cores ran at a few percent of its speed (docs/benchmarks.md, "Layout per core count")."""
    if learner_threads > 0:
        return learner_threads
    return min(2, cores) if is_gpu(learner_device) else max(1, cores - 2)
