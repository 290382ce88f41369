"""`higher-reproduce [EXPERIMENT ...]`: run the paper's experiments as one plan, then draw its figures and
write results.md. `make reproduce -- --dry-run` prints the plan and its estimated cost without running."""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

from higher_dist.config import ConfigError, is_babyai_world
from higher_dist.config_flags import positive_int, world_name
from higher_dist.config_presets import make_config
from higher_dist.launch.layout import available_cores, machine
from higher_dist.paths import ensure_folder
from higher_dist.reproduce import plan as plan_mod
from higher_dist.reproduce.archive import archive as archive_runs
from higher_dist.reproduce.claims import write_results
from higher_dist.reproduce.executor import Executor
from higher_dist.reproduce.figures import draw_all
from higher_dist.reproduce.status import estimate, human_seconds
from higher_dist.reproduce.view import make_view


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        "higher-reproduce", description="Reproduce the paper's experiments: a resumable plan of runs, "
        "its figures and results.md.",
        epilog="Experiments: main (DQN, DQN+HER, DQN+HIGhER, DQN+reward), noise (DQN+HER with attribute noise "
               "p in 0, 0.2, 0.5, 0.8, against DQN), trigger (HIGhER's generator switched on after 0, 1000, 2000 "
               "pairs), generator (exact match vs 1k..5k expert pairs). On a BabyAI level: main without DQN+reward, "
               "and trigger. Rerun the same command to resume.")
    p.add_argument("experiments", nargs="*", metavar="EXPERIMENT", help=f"any of {', '.join(plan_mod.EXPERIMENTS)} "
                   "(default: all)")
    p.add_argument("--seeds", type=positive_int, default=plan_mod.PAPER_SEEDS, help="seeds per method (paper: 5)")
    p.add_argument("--frames", type=positive_int, default=None,
                   help="env frames per run (default: the paper's 5000000; a BabyAI level's own budget, "
                        "1000000; 1e5 style accepted)")
    p.add_argument("--profile", choices=plan_mod.PROFILES, default="paper",
                   help="paper: the paper's settings; default: this project's defaults")
    p.add_argument("--parallel", type=positive_int, default=None,
                   help="runs at once (default: one per core this process may use, its CPU affinity and "
                        f"cgroup quota: {plan_mod.default_parallel()})")
    p.add_argument("--out", default="runs/reproduce", help="the plan's folder (plan.json, runs/, figures/, results.md)")
    p.add_argument("--world", type=world_name, default="paper", metavar="WORLD",
                   help="paper, small (a quick world for smoke tests) or a BabyAI pickup, go-to or open level id")
    p.add_argument("--methods", default=None, metavar="LIST",
                   help="only these variants or presets, comma-separated (e.g. dqn,her)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="a config override for every run")
    p.add_argument("--actors", type=positive_int, default=None,
                   help="actors per run (default: the layout for the cores each run gets, launch/layout.py)")
    p.add_argument("--generator-steps", type=positive_int, default=plan_mod.GENERATOR_STEPS,
                   help="Adam steps per generator run")
    p.add_argument("--dry-run", action="store_true", help="print the plan and its estimated cost; run nothing")
    p.add_argument("--print-config", action="store_true",
                   help="print the resolved config of every cluster run of the plan as JSON (run name -> config) "
                        "and exit")
    p.add_argument("--report", action="store_true", help="only draw the figures and write results.md from --out")
    p.add_argument("--no-report", action="store_true", help="do not draw figures and results.md at the end")
    p.add_argument("--archive", default=None, metavar="DEST",
                   help="only copy --out's finished runs, small enough for git (config, result, thinned metrics), "
                        "and its plan.json to DEST; DEST is a plan folder that --report reads and a copy of resumes")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return _main(args, sys.argv[1:] if argv is None else argv)
    except ConfigError as e:
        print(f"higher-reproduce: error: {e}", file=sys.stderr)
        return 2


def _main(args: argparse.Namespace, argv: list[str]) -> int:
    out = Path(args.out)
    if args.report:
        return report(out)
    if args.archive:
        return archive(out, Path(args.archive))
    for item in args.set:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected FIELD=VALUE")
    if args.frames is None:  # the world's own budget: the paper's 5M frames, a BabyAI level's 1M
        args.frames = make_config("her", args.world).frames if is_babyai_world(args.world) else plan_mod.PAPER_FRAMES
    parallel = args.parallel or plan_mod.default_parallel()
    experiments, notes = plan_mod.experiments_for(args.world, args.experiments)
    for note in notes:
        print(f"higher-reproduce: note: {note}")
    plan = plan_mod.build_plan(
        out, experiments, args.seeds, args.frames, args.world, args.profile,
        parallel, methods=[m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None,
        sets=args.set, actors=args.actors, generator_steps=args.generator_steps,
        command=["higher-reproduce", *argv])
    configs = plan_mod.check_configs(plan)
    spis = {name: cfg.replay.samples_per_insert for name, cfg in configs.items()}
    if args.print_config:
        print(json.dumps({name: cfg.to_dict() for name, cfg in configs.items()}, indent=2))
        return 0
    if args.dry_run:
        print_plan(plan, spis, parallel)
        return 0
    _lock(out)
    plan.settings["machine"] = machine()
    recorded = plan_mod.merge_and_write(plan)
    _, _, rates = estimate(plan, plan.runs, spis, parallel)
    view = make_view()
    view.event(f"plan written to {out / 'plan.json'}: {len(plan.runs)} runs, {parallel} at once")
    code = Executor(recorded, plan.runs, parallel, view, rates.fps).run()
    if code >= 128:
        view.event(f"stopped; rerun the same command to resume ({' '.join(['higher-reproduce', *argv])})")
        return code
    if not args.no_report:
        report(out)
    return code


def _lock(out: Path) -> None:
    """One higher-reproduce per folder: a second one would start the same runs twice."""
    import psutil

    lock = out / "reproduce.pid"
    try:
        pid = int(lock.read_text())
        running = pid != os.getpid() and "reproduce" in " ".join(psutil.Process(pid).cmdline())
    except (OSError, ValueError, psutil.Error):
        running = False  # no lock, or its process is gone: the folder is free
    if running:
        raise ConfigError(f"--out {out}: higher-reproduce (pid {pid}) is already running this plan")
    try:
        ensure_folder(out, "--out")
    except ValueError as e:
        raise ConfigError(str(e)) from None
    lock.write_text(str(os.getpid()))


def print_plan(plan: plan_mod.Plan, spis: dict[str, float], parallel: int) -> None:
    rows, wall, rates = estimate(plan, plan.runs, spis, parallel)
    s = plan.settings
    print(f"higher-reproduce plan for {plan.out}: experiments {', '.join(plan.experiments)}; world {s['world']}; "
          f"profile {s['profile']}; {plan_mod.seeds_text(s['seeds'])}; {s['frames']:,} frames "
          f"per run (the paper: {plan_mod.PAPER_SEEDS} seeds x {plan_mod.PAPER_FRAMES:,} frames)")
    own = plan_mod.profile_flags(s["profile"])
    print(f"  profile flags of every run: {' '.join(own) or '(none)'}")
    print(f"{'run':<24}{'kind':<10}{'experiments':<14}{'budget':>12}{'state':>11}{'estimate':>10}  run's own flags")
    for row in rows:
        run = row["run"]
        budget = f"{run.pairs} pairs" if run.kind == "generator" else f"{run.frames:,}"
        flags = " ".join(run.flags[len(own):]) + (f" --actors {run.actors}" if run.kind == "cluster"
                                                  else f" --steps {run.steps}")
        print(f"{run.name:<24}{run.kind:<10}{','.join(run.experiments):<14}{budget:>12}{row['state']:>11}"
              f"{human_seconds(row['seconds']):>10}  {flags.strip()}")
    cluster = [r for r in rows if r["run"].kind == "cluster"]
    left = sum(r["left"] for r in cluster)
    print(f"\n{len(rows)} runs ({len(cluster)} cluster runs, {len(rows) - len(cluster)} generator runs); "
          f"{left:,} env frames left to run")
    print(f"estimated cost on this machine ({available_cores()} cores to use, {platform.machine()}): "
          f"{human_seconds(wall)} wall-clock at --parallel {parallel}")
    print(f"  frame rate used: {rates.fps:.0f} frames/s per run at {rates.spi:g} samples per insert, {rates.source}")
    print(f"  generator runs: {rates.gen_source}")
    print("nothing was run (--dry-run); without it the plan is written to "
          f"{plan.out / 'plan.json'} and run, finished runs skipped and interrupted ones resumed")


def archive(out: Path, dest: Path) -> int:
    recorded = plan_mod.read_plan(out)
    try:
        names = archive_runs(recorded, dest)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    left = len(recorded.runs) - len(names)
    print(f"{dest}: {len(names)} finished runs archived; {left} not finished (not archived)")
    return 0


def report(out: Path) -> int:
    recorded = plan_mod.read_plan(out)
    figures = draw_all(recorded)
    path = write_results(recorded, figures)
    for f in figures.values():
        print(f)
    print(path)
    return 0
