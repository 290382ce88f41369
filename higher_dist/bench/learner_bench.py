"""Learner speed: samples/s at batch 64, 128, 256, and what each speed lever is worth.

Every row runs the learner's real step, `Learner.update`: prioritized sampling from a full
100k-transition replay of random but valid episodes, the DQN step (forwards, backward, clipping, Adam,
target update) and the priority update. A row is one setting of the levers of `DQNConfig` (compile,
joint_online, prefetch) plus bf16 autocast, which is not a config field (it measured slower here).
`--levers` measures each lever switched on alone against all of them off, then the defaults; rows are
run round-robin `--repeat` times (A/B interleaved, so a neighbour's load hits every row alike) and
the median is reported. Alongside wall-clock samples/s it reports CPU samples/s (CPU time of the whole
process, prefetch thread included), which moves less with the machine's load. Compiling happens
before timing (synchronously) and its seconds are printed. Then the compute bound at the default batch
(bench/compute_bound.py: FLOPs per sample counted on the real loss, the GFLOP/s one thread reaches on
those ops alone) and each row's CPU samples/s as a share of it. `--set network.FIELD=VALUE` (any config
field) changes the config every row runs. The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import sys
import time
from types import SimpleNamespace

import numpy as np
import torch

from higher_dist.bench import compute_bound
from higher_dist.config import DQNConfig, NetworkConfig
from higher_dist.learning.dqn import DQNUpdater
from higher_dist.learning.networks import count_parameters
from higher_dist.world.spec import DEFAULT_SPEC, VIEW_CHANNEL_VALUES

BATCH_SIZES = (64, 128, 256)
VOCAB_SIZE = DEFAULT_SPEC.vocab_size
MISSION_LEN = 10
_POOL = 8  # distinct batches cycled per size: varied inputs without generation inside the timing


def synthetic_batch(rng: np.random.Generator, batch_size: int, frame_stack: int, view_size: int = 7,
                    gamma: float = 0.99, n_step: int = 3) -> SimpleNamespace:
    """A TransitionBatch look-alike: object cells carry attributes, other cells zeros; missions of
    6..8 words (the real prefixes' range) padded with PAD; a third of the windows terminal."""
    def views() -> np.ndarray:
        shape = (batch_size, frame_stack, view_size, view_size)
        out = np.zeros(shape + (4,), np.uint8)
        kind = rng.choice(5, size=shape, p=[0.3, 0.5, 0.1, 0.05, 0.05])
        out[..., 0] = kind
        for ch in (1, 2, 3):
            out[..., ch] = np.where(kind >= 3, rng.integers(1, VIEW_CHANNEL_VALUES[ch], shape), 0)
        return out

    mission = np.zeros((batch_size, MISSION_LEN), np.int64)
    for i, n in enumerate(rng.integers(6, 9, batch_size)):
        mission[i, :n] = rng.integers(3, VOCAB_SIZE, n)
    terminal = rng.random(batch_size) < 1 / 3
    return SimpleNamespace(
        indices=np.arange(batch_size, dtype=np.int64), generations=np.zeros(batch_size, np.int64),
        obs=views(), mission=mission, action=rng.integers(0, 4, batch_size),
        reward=(terminal & (rng.random(batch_size) < 0.5)).astype(np.float32),
        discount=np.where(terminal, 0.0, gamma ** n_step).astype(np.float32), next_obs=views(),
        weights=rng.uniform(0.3, 1.0, batch_size).astype(np.float32),
    )


def measure(learner: DQNUpdater, batches: list[SimpleNamespace], seconds: float, warmup: int) -> dict[str, float]:
    for i in range(warmup):
        learner.update(batches[i % len(batches)])
    n = 0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    while True:
        learner.update(batches[n % len(batches)])
        n += 1
        wall = time.perf_counter() - wall0
        if wall >= seconds:
            break
    cpu = time.process_time() - cpu0
    b = len(batches[0].action)
    return {"updates_per_s": n / wall, "samples_per_s": n * b / wall, "ms_per_update": 1e3 * wall / n,
            "cpu_ms_per_update": 1e3 * cpu / n, "cpu_samples_per_s": n * b / cpu, "updates": n}


def _parse_override(text: str) -> tuple[str, object]:
    """`name=value` for a NetworkConfig field; tuples as comma lists (conv_channels=16,32)."""
    name, _, value = text.partition("=")
    fields = {f.name: f for f in dataclasses.fields(NetworkConfig)}
    if name not in fields or not value:
        raise argparse.ArgumentTypeError(f"--net expects FIELD=VALUE with FIELD in {sorted(fields)}")
    default = getattr(NetworkConfig(), name)
    if isinstance(default, tuple):
        return name, tuple(int(v) for v in value.split(",") if v)
    if isinstance(default, bool):
        return name, value.lower() in ("1", "true", "yes")
    if isinstance(default, int):
        return name, int(value)
    return name, value


def synthetic_episode(rng: np.random.Generator, length: int, view_size: int = 7):
    """A random but valid episode (view values in range, a mission of words) for filling a replay."""
    from higher_dist.learning.episode import SUCCESS, TIMEOUT, WRONG_PICK, Episode

    maxima = np.array([5, 7, 6, 6])
    frames = (rng.random((length + 1, view_size, view_size, 4)) * maxima).astype(np.uint8)
    outcome = int(rng.choice([SUCCESS, WRONG_PICK, TIMEOUT]))
    rewards = np.zeros(length, np.float32)
    rewards[-1] = 1.0 if outcome == SUCCESS else 0.0
    from higher_dist.world.language import VOCAB

    words = rng.integers(3, len(VOCAB), size=int(rng.integers(5, 9)))
    mission = np.zeros(10, np.int64)
    mission[: words.size] = words
    return Episode(frames=frames, actions=rng.integers(0, 4, length).astype(np.uint8), rewards=rewards,
                   mission=mission, outcome=outcome, picked=np.full(4, -1, np.int8), goal=np.zeros(4, np.int8))


def fill_replay(replay, max_steps: int, seed: int = 0) -> None:
    """Fill a replay to its capacity with random but valid episodes (64 of them, drawn again and again)."""
    rng = np.random.default_rng(seed)
    pool = [synthetic_episode(rng, int(rng.integers(5, max_steps + 1))) for _ in range(64)]
    added = 0
    while added < replay.capacity:
        episode = pool[int(rng.integers(len(pool)))]
        replay.add_episode(episode)
        added += episode.length + 1  # a slot per frame, the last one included


@dataclasses.dataclass(frozen=True)
class Lever:
    """One row of the table: DQNConfig overrides plus bf16 autocast."""
    name: str
    compile: bool = False
    joint_online: bool = False
    prefetch: bool = False
    bf16: bool = False

    def dqn_overrides(self) -> dict[str, bool]:
        return {"dqn.compile": self.compile, "dqn.joint_online": self.joint_online, "dqn.prefetch": self.prefetch}


def default_lever() -> Lever:
    from higher_dist.config import DQNConfig

    d = DQNConfig()
    return Lever("defaults", compile=d.compile, joint_online=d.joint_online, prefetch=d.prefetch)


def lever_rows() -> list[Lever]:
    return [
        Lever("eager (all levers off)"),
        Lever("+ joint online forward", joint_online=True),
        Lever("+ prefetch", prefetch=True),
        Lever("+ bf16 autocast", bf16=True),
        Lever("+ compile", compile=True),
        Lever("+ compile + joint", compile=True, joint_online=True),
        default_lever(),
    ]


def make_core(batch_size: int, lever: Lever, cfg=None, threads: int = 1):
    """A Learner with a full replay of synthetic episodes, its loss compiled when the lever says so.
    Returns (core, seconds spent compiling or None)."""
    from higher_dist.config import override
    from higher_dist.config_presets import make_config
    from higher_dist.learning.learner import Learner

    cfg = cfg or make_config("higher", "paper")
    cfg = override(cfg, **{"dqn.batch_size": batch_size, "replay.capacity": 100_000, **lever.dqn_overrides()})
    torch.set_num_threads(max(1, threads))
    core = Learner(cfg)
    fill_replay(core.replay, cfg.world.max_steps)
    compile_s = None
    if core.dqn.compiled is not None:
        t0 = time.perf_counter()
        batch = core.replay.sample(batch_size, 1.0)
        core.dqn.compiled.start(core.dqn._tensors(batch), background=False)
        compile_s = time.perf_counter() - t0
        if core.dqn.compiled.failed:
            print(f"compile failed, the row runs eager: {core.dqn.compiled.failed}")
    return core, compile_s


def time_updates(core, seconds: float, warmup: int = 5, bf16: bool = False) -> dict[str, float]:
    """Wall and CPU samples/s of `core.update` over `seconds` of wall time."""
    autocast = torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()
    with autocast:
        for _ in range(warmup):
            core.update()
        n, sampled0 = 0, core.limiter.sampled  # samples as the ratio counts them (a recurrent batch varies)
        wall0, cpu0 = time.perf_counter(), time.process_time()
        while time.perf_counter() - wall0 < seconds:
            core.update()
            n += 1
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    samples = core.limiter.sampled - sampled0
    return {"samples_per_s": samples / wall, "cpu_samples_per_s": samples / cpu, "updates_per_s": n / wall}


def measure_updates_per_s(batch_size: int, seconds: float = 5.0, cfg=None, warmup: int = 5, threads: int = 1) -> float:
    """Updates/s of the learner alone, through the same path as in the cluster (Learner.update,
    with the config's levers, compiled before timing), on `threads` torch threads."""
    from higher_dist.config_presets import make_config

    cfg = cfg or make_config("higher", "paper")
    d = cfg.dqn
    core, _ = make_core(batch_size, Lever("config", d.compile, d.joint_online, d.prefetch), cfg,
                        cfg.torch_threads or threads)
    try:
        return time_updates(core, seconds, warmup)["updates_per_s"]
    finally:
        core.close()


def run_table(levers: list[Lever], sizes: list[int], seconds: float, repeat: int, threads: int,
              cfg=None, bound_size: int | None = None) -> dict:
    """Round-robin over (lever, size) `repeat` times; medians per cell. With `bound_size`, also the
    compute bound on a batch the first row's core samples at that size (under the key "bound")."""
    cores, compile_s = {}, {}
    for lever in levers:
        for b in sizes:
            cores[lever, b], compile_s[lever, b] = make_core(b, lever, cfg, threads=threads)
    runs: dict[tuple, list[dict]] = {key: [] for key in cores}
    figures = None
    try:
        for _ in range(repeat):
            for key, core in cores.items():
                runs[key].append(time_updates(core, seconds, bf16=key[0].bf16))
        core = cores.get((levers[0], bound_size))
        if core is not None and not core.recurrent:  # FLOPs are counted for the frame-stack network
            figures = compute_bound.bound(core.dqn, core.dqn._tensors(core.replay.sample(bound_size, 1.0)))
    finally:
        for core in cores.values():
            core.close()
    table = {}
    for (lever, b), rs in runs.items():
        table[lever.name, b] = {
            "samples_per_s": statistics.median(r["samples_per_s"] for r in rs),
            "updates_per_s": statistics.median(r["updates_per_s"] for r in rs),
            "cpu_samples_per_s": statistics.median(r["cpu_samples_per_s"] for r in rs),
            "runs": [round(r["samples_per_s"]) for r in rs], "compile_s": compile_s[lever, b],
        }
    table["bound"] = figures
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="higher-bench learner", description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per cell and round")
    parser.add_argument("--repeat", type=int, default=1, help="round-robin rounds; the median is reported")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--batch-sizes", default=",".join(map(str, BATCH_SIZES)))
    parser.add_argument("--levers", action="store_true", help="every lever alone, then the defaults")
    parser.add_argument("--only", nargs="*", metavar="LEVER", choices=["compile", "joint", "prefetch", "bf16"],
                        help="one row with just these levers on (e.g. --only compile prefetch)")
    parser.add_argument("--net", type=_parse_override, action="append", default=[], metavar="FIELD=VALUE",
                        help="network shape, raw network step only: --net frame_stack=1 --net conv_channels=16,32")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="overrides",
                        help="any config field for every row, e.g. --set network.film_blocks=1 (JSON value)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    sizes = [int(s) for s in args.batch_sizes.split(",") if s]
    if args.net:
        return _network_shape(args, sizes)
    cfg = bench_config(args.overrides)
    if args.levers:
        levers = lever_rows()
    elif args.only is not None:
        on = set(args.only)
        levers = [Lever("+ " + " + ".join(sorted(on)) if on else "eager (all levers off)", compile="compile" in on,
                        joint_online="joint" in on, prefetch="prefetch" in on, bf16="bf16" in on)]
    else:
        levers = [Lever("eager (all levers off)"), default_lever()]
    print(f"learner bench: {args.threads} thread(s), torch {torch.__version__}, "
          f"{count_parameters(DQNUpdater(cfg.network, DQNConfig(compile=False)).online)} parameters, "
          f"full prioritized replay, median of {args.repeat} interleaved round(s) of {args.seconds:g} s")
    if args.overrides:
        print("config overrides: " + " ".join(args.overrides))
    bound_size = DQNConfig().batch_size if DQNConfig().batch_size in sizes else max(sizes)
    table = run_table(levers, sizes, args.seconds, args.repeat, args.threads, cfg, bound_size)
    head = "".join(f"{'B=' + str(b):>10}" for b in sizes)
    print(f"{'samples/s (wall)':<28}{head}   {'cpu samples/s':>14} at B=" + "/".join(map(str, sizes)))
    summary: dict[str, object] = {"threads": args.threads, "repeat": args.repeat, "rows": {}}
    for lever in levers:
        cells = [table[lever.name, b] for b in sizes]
        compile_note = [c["compile_s"] for c in cells if c["compile_s"] is not None]
        note = f"   (compile {max(compile_note):.0f} s)" if compile_note else ""
        print(f"{lever.name:<28}" + "".join(f"{c['samples_per_s']:>10,.0f}" for c in cells) + "   "
              + "/".join(f"{c['cpu_samples_per_s']:,.0f}" for c in cells) + note)
        summary["rows"][lever.name] = {f"b{b}": {k: (round(v) if isinstance(v, float) else v) for k, v in c.items()}
                                       for b, c in zip(sizes, cells)}
    defaults = next((lv for lv in levers if lv.name == "defaults"), levers[-1])
    for b in sizes:
        cell = table[defaults.name, b]
        summary[f"b{b}_samples_per_s"] = round(cell["samples_per_s"])
        summary[f"b{b}_updates_per_s"] = round(cell["updates_per_s"], 1)
        summary[f"b{b}_cpu_samples_per_s"] = round(cell["cpu_samples_per_s"])
    figures = table["bound"]
    measured = {lv.name: table[lv.name, bound_size]["cpu_samples_per_s"] for lv in levers}
    if figures is None:
        print("compute bound: counted for the frame-stack network only (network.core=stack)")
    else:
        print("\n".join(compute_bound.bound_lines(figures, bound_size, measured)))
        summary["bound"] = {"batch_size": bound_size, **{k: round(v, 1) for k, v in figures.items()},
                            "ratio": round(measured[defaults.name] / figures["bound_samples_per_s"], 3)}
        summary["bound_ratio"] = summary["bound"]["ratio"]  # the defaults' CPU samples/s over the bound
    summary["network"] = dataclasses.asdict(cfg.network)
    print(json.dumps(summary))
    return 0


def bench_config(overrides: list[str]):
    """The paper-world `higher` config every row runs, with `--set FIELD=VALUE` overrides (validated)."""
    from higher_dist.config_flags import explicit_overrides
    from higher_dist.config_presets import make_config

    # make_config applies the overrides, then the declared types and validation, as a run gets them.
    return make_config("higher", "paper", **explicit_overrides(argparse.Namespace(set=overrides)))


def _network_shape(args, sizes: list[int]) -> int:
    """The raw DQN step (synthetic batches, no replay) for a network shape, eager: the figure a shape
    change is judged by before a learning run decides whether it keeps its success."""
    torch.set_num_threads(args.threads)
    net_cfg = dataclasses.replace(NetworkConfig(), **dict(args.net))
    if net_cfg.recurrent:  # synthetic transitions carry frame stacks, not whole episodes
        print(f"higher-bench learner: --net core={net_cfg.core} is measured on whole episodes from replay: "
              f"use --set network.core={net_cfg.core}", file=sys.stderr)
        return 2
    dqn_cfg = DQNConfig(compile=False)
    rng = np.random.default_rng(args.seed)
    print(f"network {dataclasses.asdict(net_cfg)}, "
          f"{count_parameters(DQNUpdater(net_cfg, dqn_cfg).online)} parameters, eager")
    summary: dict[str, object] = {"network": dataclasses.asdict(net_cfg)}
    for b in sizes:
        learner = DQNUpdater(net_cfg, dqn_cfg, seed=args.seed)
        batches = [synthetic_batch(rng, b, net_cfg.frame_stack, gamma=dqn_cfg.gamma, n_step=dqn_cfg.n_step)
                   for _ in range(_POOL)]
        r = measure(learner, batches, args.seconds, 10)
        figures = compute_bound.bound(learner, learner._tensors(batches[0]))
        print(f"B={b:<5} {r['samples_per_s']:>10,.0f} samples/s   {r['cpu_samples_per_s']:>10,.0f} cpu samples/s   "
              f"{figures['flops_per_sample'] / 1e6:.3f} MFLOP/sample, bound {figures['bound_samples_per_s']:,.0f} "
              f"({r['cpu_samples_per_s'] / figures['bound_samples_per_s']:.0%})")
        summary[f"b{b}_samples_per_s"] = round(r["samples_per_s"])
        summary[f"b{b}_bound_samples_per_s"] = round(figures["bound_samples_per_s"])
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
