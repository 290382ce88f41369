"""The plan: which runs each of the paper's experiments needs, with which flags, and where they stand.

A run is one `higher-cluster` process tree (kind "cluster") or one generator measurement (kind
"generator"). Runs are named by what they are (`her-s0`, `noisy-her-p0.5-s1`, `gen-pairs3000-s0`),
so experiments that need the same run share it (the noise figure's DQN line is `main`'s DQN) and a
second invocation with the same --out finds the runs of the first. The plan is written to
DIR/plan.json before anything runs.

On a BabyAI level (`--world BabyAI-...`) only what exists there is planned: `main` without DQN+reward
(reward shaping is FetchAttr's; a level gives its own reward) and `trigger`. `noise` (noisy-her's
attribute noise) and `generator` (the generator on FetchAttr's expert pairs) are FetchAttr's own:
asked for by name they are refused, and "all experiments" leaves them out with a note.

The paper's settings come from higher-cluster's `--profile paper` (config.py `paper_profile`); the
default profile passes nothing, so a run gets this project's defaults.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from higher_dist.config import Config, ConfigError, is_babyai_world
from higher_dist.config_flags import add_config_flags, config_from_args
from higher_dist.config_presets import make_config
from higher_dist.launch import layout
from higher_dist.resume import CHANGEABLE_ON_RESUME, saved_config
from higher_dist.rundir import atomic_write_bytes
from higher_dist.world.spec import WorldSpec

EXPERIMENTS = ("main", "noise", "trigger", "generator")
PROFILES = ("paper", "default")
PAPER_FRAMES = 5_000_000  # env frames per run in the paper's figures
PAPER_SEEDS = 5
NOISE_LEVELS = (0.2, 0.5, 0.8)  # p = 0 is DQN+HER itself
TRIGGER_PAIRS = (0, 1000, 2000)
GENERATOR_PAIRS = (1000, 2000, 3000, 4000, 5000)
PAPER_GENERATOR_EXACT = {1000: 0.18, 5000: 0.70}  # the paper's exact match from that many expert pairs
GENERATOR_STEPS = 1500  # Adam steps per generator measurement (as `higher-bench generator`)
GENERATOR_EVAL_PAIRS = 1000  # fresh pairs per goal set (seen, unseen)
# What each invocation on one folder adds to plan.json's settings: the report names every command that
# ran the plan and every machine it ran on, not only the latest (list key: the invocation's own key).
HISTORY = {"commands": "command", "machines": "machine"}
EVALS_PER_RUN = 10  # at least this many greedy evaluations per run, whatever its budget

# (variant, preset, label, extra --set overrides) of each experiment
MAIN = (("dqn", "dqn", "DQN", ()), ("her", "her", "DQN+HER", ()), ("higher", "higher", "DQN+HIGhER", ()),
        ("reward", "reward", "DQN+reward", ()))
NOISE = ((("her", "her", "DQN+HER", ()),)
         + tuple((f"noisy-her-p{p}", "noisy-her", f"DQN+HER noisy p={p}", (f"relabel.noise_p={p}",))
                 for p in NOISE_LEVELS)
         + (("dqn", "dqn", "DQN", ()),))
# The trigger runs store every failure until the generator starts, as the paper's do: kept out of the
# replay until 2000 pairs, the agent would learn from successes alone for most of the run.
TRIGGER = tuple((f"higher-trigger{n}", "higher", f"DQN+HIGhER from {n} pairs",
                 (f"generator.n_min={n}", "generator.min_accuracy=0", "relabel.withheld_while_gated=false"))
                for n in TRIGGER_PAIRS)

# What a BabyAI level cannot run, and why.
NOT_ON_BABYAI = {
    "noise": "it varies noisy-her's attribute noise, which is defined on FetchAttr's four attributes",
    "generator": "it measures the generator on FetchAttr's expert pairs and held-out goals",
}
NOT_ON_BABYAI_VARIANTS = {"reward": "DQN+reward shapes FetchAttr's reward; a BabyAI level gives its own"}


@dataclass(frozen=True)
class RunSpec:
    name: str  # folder under DIR/runs and key in plan.json
    kind: str  # cluster | generator
    variant: str  # what is run, seeds aside: her, noisy-her-p0.5, gen-pairs1000
    label: str  # legend and table label
    preset: str
    seed: int
    world: str
    frames: int = 0  # cluster: env frames budget
    flags: tuple[str, ...] = ()  # cluster / generator flags beyond the above (--set, --profile)
    actors: int = 1  # cluster: actor processes (kept from the first plan when a run is resumed)
    eval_every: int = 0  # cluster: frames between greedy evaluations; 0 keeps the config's
    pairs: int = 0  # generator: expert training pairs
    steps: int = 0  # generator: Adam steps
    experiments: tuple[str, ...] = ()

    def cluster_flags(self) -> list[str]:
        """The higher-cluster config flags of this run (no run dir, ports or --resume)."""
        evals = ["--set", f"eval.every_frames={self.eval_every}"] if self.eval_every else []
        return ["--preset", self.preset, "--world", self.world, "--seed", str(self.seed),
                "--frames", str(self.frames), "--actors", str(self.actors), *evals, *self.flags]

    def same_run(self, other: "RunSpec") -> bool:
        """Whether `other` is this run, aside from what a resume may change: the budget (a resume
        extends it), the evaluation interval, the actor count and the experiments that use it."""
        def key(r: RunSpec) -> RunSpec:
            return replace(r, frames=0, actors=1, eval_every=0, experiments=())

        return key(self) == key(other)


@dataclass
class Plan:
    out: Path
    runs: list[RunSpec]
    experiments: dict[str, list[str]]  # experiment -> run names, in figure order
    settings: dict[str, Any]  # world, profile, seeds, frames, parallel, command

    def path(self, run: RunSpec) -> Path:
        return self.out / "runs" / run.name

    def to_json(self) -> str:
        return json.dumps({"version": 1, "settings": self.settings, "experiments": self.experiments,
                           "runs": {r.name: asdict(r) for r in self.runs}}, indent=2)


def seeds_text(n: int) -> str:
    """'1 seed', '3 seeds': how every table, legend and reason counts seeds."""
    return f"{n} seed{'s' * (n != 1)}"


# -- the profile -------------------------------------------------------------------------------------
def profile_flags(profile: str) -> tuple[str, ...]:
    """The higher-cluster flags of a profile (the generator runs read the same config)."""
    if profile not in PROFILES:
        raise ConfigError(f"--profile: must be one of {', '.join(PROFILES)}, got {profile!r}")
    return () if profile == "default" else ("--profile", profile)


# -- building the plan -------------------------------------------------------------------------------
def experiments_for(world: str, asked: list[str] | None) -> tuple[list[str], list[str]]:
    """(the experiments to plan, notes on what is left out). `asked` None or empty means all of them:
    on a BabyAI level that leaves out those it cannot run, each with a note; asked by name, they are
    refused (build_plan)."""
    if not is_babyai_world(world):
        return list(asked or EXPERIMENTS), []
    chosen = list(asked) if asked else [e for e in EXPERIMENTS if e not in NOT_ON_BABYAI]
    notes = [] if asked else [f"{e} skipped on {world}: {why}" for e, why in NOT_ON_BABYAI.items()]
    if "main" in chosen:
        notes += [f"main on {world} without {v}: {why}" for v, why in NOT_ON_BABYAI_VARIANTS.items()]
    return chosen, notes


def default_parallel() -> int:
    """Runs at once that fit this machine: one per core this process may use (its affinity and cgroup
    quota, as the run layout counts them). A run's roles wait on each other (the learner on experience,
    the actor on weights), so one run alone leaves part of the machine idle; on the 2-core development
    machine two runs at a time each ran at 1,200-1,750 frames/s (docs/results.md, "How it was measured")."""
    return layout.available_cores()


def default_actors(parallel: int) -> int:
    return layout.default_actors(max(1, layout.available_cores() // parallel))


def learner_threads(parallel: int, actors: int) -> int:
    """Each of `parallel` runs lays out its share of the cores, not the whole machine (oversubscribed
    learners would each slow the others down)."""
    return layout.plan_layout(max(1, layout.available_cores() // parallel), actors).learner_threads


def build_plan(out: str | os.PathLike, experiments: list[str], seeds: int, frames: int, world: str,
               profile: str, parallel: int, methods: list[str] | None = None, sets: list[str] = (),
               actors: int | None = None, generator_steps: int = GENERATOR_STEPS,
               command: list[str] | None = None) -> Plan:
    """The runs of `experiments`; `methods` keeps only those variants (or presets) of the cluster runs."""
    bad = [e for e in experiments if e not in EXPERIMENTS]
    if bad:
        raise ConfigError(f"experiment: unknown {bad}; choose from {', '.join(EXPERIMENTS)}")
    babyai = is_babyai_world(world)
    for experiment in experiments:
        if babyai and experiment in NOT_ON_BABYAI:
            raise ConfigError(f"experiment {experiment}: not on a BabyAI level ({world}): {NOT_ON_BABYAI[experiment]}")
    if seeds < 1 or frames < 1 or parallel < 1 or generator_steps < 1:
        raise ConfigError("--seeds, --frames, --parallel and --generator-steps must be >= 1")
    actors = actors or default_actors(parallel)
    eval_every = _eval_every(world, frames)
    common = ["--threads", str(learner_threads(parallel, actors)), *(x for s in sets for x in ("--set", s))]
    by_name: dict[str, RunSpec] = {}
    order: dict[str, list[str]] = {}
    tables = {"main": MAIN, "noise": NOISE, "trigger": TRIGGER}
    for experiment in experiments:
        names = order.setdefault(experiment, [])
        for seed in range(seeds):
            if experiment == "generator":
                for pairs in GENERATOR_PAIRS:
                    variant = f"gen-pairs{pairs}"
                    if methods and variant not in methods and "generator" not in methods:
                        continue
                    _add(by_name, names, RunSpec(
                        f"{variant}-s{seed}", "generator", variant, f"{pairs} expert pairs", "higher", seed, world,
                        flags=(*profile_flags(profile), *common), pairs=pairs, steps=generator_steps,
                        experiments=(experiment,)))
                continue
            for variant, preset, label, extra in tables[experiment]:
                if methods and variant not in methods and preset not in methods:
                    continue
                if babyai and variant in NOT_ON_BABYAI_VARIANTS:
                    continue
                flags = (*profile_flags(profile), *(x for s in extra for x in ("--set", s)), *common)
                _add(by_name, names, RunSpec(f"{variant}-s{seed}", "cluster", variant, label, preset, seed, world,
                                             frames=frames, flags=flags, actors=actors, eval_every=eval_every or 0,
                                             experiments=(experiment,)))
    if not by_name:
        raise ConfigError(f"--methods {','.join(methods or [])}: selects no run of {', '.join(experiments)}")
    # Seed-major: every method's first seed before any second seed, so a stopped plan has comparable runs.
    runs = sorted(by_name.values(), key=lambda r: (r.seed, list(by_name).index(r.name)))
    settings = {"world": world, "profile": profile, "seeds": seeds, "frames": frames,
                "parallel": parallel, "actors_per_run": actors, "generator_steps": generator_steps,
                "sets": list(sets), "command": command or [], "created": time.strftime("%Y-%m-%d %H:%M:%S")}
    return Plan(Path(out), runs, order, settings)


def _add(by_name: dict[str, RunSpec], names: list[str], spec: RunSpec) -> None:
    old = by_name.get(spec.name)
    if old is not None:
        spec = replace(old, experiments=old.experiments + tuple(e for e in spec.experiments if e not in old.experiments))
    by_name[spec.name] = spec
    if spec.name not in names:
        names.append(spec.name)


def _eval_every(world: str, frames: int) -> int | None:
    """A greedy evaluation interval that gives a short run EVALS_PER_RUN points; None keeps the config's."""
    default = make_config("dqn", world).eval.every_frames
    wanted = max(500, frames // EVALS_PER_RUN)
    return wanted if wanted < default else None


def check_configs(plan: Plan) -> dict[str, Config]:
    """Every run's config, built exactly as higher-cluster will build it: a bad --set or value is
    refused now, naming it, rather than in the middle of the plan."""
    parser = argparse.ArgumentParser("higher-reproduce", add_help=False)
    add_config_flags(parser)
    configs: dict[str, Config] = {}
    for run in plan.runs:
        argv = (run.cluster_flags() if run.kind == "cluster"
                else ["--preset", "higher", "--world", run.world, "--seed", str(run.seed), *run.flags])
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            raise ConfigError(f"run {run.name}: flags refused: {' '.join(argv)}") from None
        cfg = config_from_args(args)
        try:  # a world that cannot be built (a BabyAI id of no supported level) is refused here
            WorldSpec.of(cfg.world)
        except ValueError as e:
            raise ConfigError(f"--world: {e}") from None
        configs[run.name] = cfg
    return configs


# -- plan.json ---------------------------------------------------------------------------------------
def load_plan_file(out: Path) -> dict[str, Any] | None:
    path = Path(out) / "plan.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}: not a plan ({e})") from None


def spec_from_dict(d: dict[str, Any]) -> RunSpec:
    d = dict(d)
    for key in ("flags", "experiments"):
        d[key] = tuple(d.get(key, ()))
    return RunSpec(**d)


def merge_and_write(plan: Plan) -> Plan:
    """Write plan.json, keeping the runs of earlier plans in the same folder (their figures stay in the
    report); returns the whole recorded plan, and `plan.runs` becomes the recorded form of its runs.
    A run planned before with other settings is refused: its folder holds another experiment."""
    old = load_plan_file(plan.out) or {}
    old_runs = {name: spec_from_dict(d) for name, d in old.get("runs", {}).items()}
    for run in plan.runs:
        previous = old_runs.get(run.name)
        if previous is not None and not run.same_run(previous) and not _holds_its_config(plan, run):
            raise ConfigError(
                f"--out {plan.out}: run {run.name} was planned there with other settings "
                f"({' '.join(previous.flags)} vs {' '.join(run.flags)}); use another --out")
    merged_runs = {**old_runs}
    for run in plan.runs:
        previous = merged_runs.get(run.name)
        exps = previous.experiments if previous else ()
        # The actor count stays the first plan's: a resumed run keeps its exploration ladder.
        merged_runs[run.name] = replace(run, actors=previous.actors if previous else run.actors,
                                        experiments=exps + tuple(e for e in run.experiments if e not in exps))
    experiments = {**old.get("experiments", {})}
    for name, names in plan.experiments.items():
        experiments[name] = list(dict.fromkeys([*experiments.get(name, []), *names]))
    settings = {**plan.settings, **{key: _union(old.get("settings", {}), plan.settings, key) for key in HISTORY}}
    merged = Plan(plan.out, list(merged_runs.values()), experiments, settings)
    plan.runs = [merged_runs[r.name] for r in plan.runs]  # what this invocation runs, as recorded
    plan.out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(plan.out / "plan.json", merged.to_json().encode())
    return merged


def _holds_its_config(plan: Plan, run: RunSpec) -> bool:
    """Whether the run's folder already holds this run: its config.json is the config `run`'s flags give
    now, aside from what a resume may change. Flags that only restate what the run had (one made explicit
    when a default changed) leave it the same run."""
    if run.kind != "cluster":
        return False
    try:
        saved = saved_config(plan.path(run))  # missing or unreadable: nothing says what the run was
    except ConfigError:
        return False
    wanted = check_configs(replace(plan, runs=[run]))[run.name]
    return _what_a_resume_keeps(saved) == _what_a_resume_keeps(wanted)


def _what_a_resume_keeps(cfg: Config) -> dict[str, Any]:
    d = {k: v for k, v in cfg.to_dict().items() if k not in CHANGEABLE_ON_RESUME}
    d["eval"] = {k: v for k, v in d["eval"].items() if k != "every_frames"}  # set per plan (EVALS_PER_RUN)
    return d


def _union(old: dict[str, Any], new: dict[str, Any], key: str) -> list:
    """Every distinct value `key` took over the invocations on one folder, oldest first."""
    single = HISTORY[key]
    values = [*old.get(key, []), *([old[single]] if single in old and not old.get(key) else []), new.get(single)]
    return [v for i, v in enumerate(values) if v and v not in values[:i]]


def read_plan(out: str | os.PathLike) -> Plan:
    """The plan recorded in a folder (for the report and the figures)."""
    data = load_plan_file(Path(out))
    if data is None:
        raise ConfigError(f"{out}: no plan.json (run higher-reproduce --out {out} first)")
    runs = [spec_from_dict(d) for d in data.get("runs", {}).values()]
    return Plan(Path(out), runs, data.get("experiments", {}), data.get("settings", {}))
