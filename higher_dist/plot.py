"""higher-plot RUN_DIR [RUN_DIR ...] --out DIR: figures from runs' metrics.jsonl.

Each run directory holds config.json ("preset", "seed", "world": {"name": ...}) and metrics.jsonl
(one record every couple of seconds, see docs/metrics.md for the keys). A
directory without metrics.jsonl but with run subdirectories (runs/ holding runs/a, runs/b) is expanded
to those runs. Runs that share a preset are seeds of one method: their curves are interpolated onto a
common frames grid and drawn as a mean with a min-max band.

Writes success_rate.png, success_rate_heldout.png (when held-out evaluations exist),
generator_accuracy.png (when a generator was trained) and replay_composition.png.

`--table` also writes each run's curve at its greedy evaluations as NAME.csv (frames, minutes, updates per
frame, exploring and greedy success with standard errors, the generator's dataset, gate and accuracies)
and prints the same as a Markdown table.

Given a `higher-reproduce` folder (one holding plan.json), the `higher-plot` command (cli.py) hands it to
`higher_dist.reproduce.cli.report` instead: that plan's figures and DIR/results.md.
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from higher_dist import metrics as m
from higher_dist.analysis.drawing import pyplot
from higher_dist.analysis.runs import (REPLAY_KEYS, NoRun, Run, find_runs, is_number, mean_band, replay_fractions,
                                      success_key)
from higher_dist.config_flags import DefaultsHelp
from higher_dist.paths import ensure_folder


def success_figure(runs: list[Run], key_for, title: str):
    """Each preset's success curve (`key_for(run)`): one run's as is, several seeds' as their mean with a
    min-max band. Returns the matplotlib Figure (main saves it)."""
    plt = pyplot()
    by_preset: dict[str, list[Run]] = defaultdict(list)
    for run in runs:
        by_preset[run.preset].append(run)
    fig, ax = plt.subplots(figsize=(8, 5))
    for i, (preset, group) in enumerate(sorted(by_preset.items())):
        colour = f"C{i % 10}"
        curves = [run.series(key_for(run)) for run in group]
        if any(key_for(run) == m.SUCCESS_TRAIN for run in group):
            preset = f"{preset} (exploring)"  # no greedy evaluation in these runs: say what is drawn
        band = mean_band(curves) if len(group) > 1 else None
        if band is not None:
            grid, mean, low, high = band
            ax.plot(grid, mean, color=colour, label=f"{preset} (mean of {len(group)} seeds)")
            ax.fill_between(grid, low, high, color=colour, alpha=0.2, linewidth=0)
        else:
            for j, (x, y) in enumerate(curves):
                ax.plot(x, y, color=colour, alpha=1.0 if j == 0 else 0.6,
                        label=preset if j == 0 else None)
    ax.set(xlabel="environment frames", ylabel="success rate", title=title, ylim=(-0.02, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return fig


def generator_figure(runs: list[Run]):
    """Each run's generator validation accuracy (solid) and relabel accuracy (dashed)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 5))
    for i, run in enumerate(runs):
        colour = f"C{i % 10}"
        x, y = run.series(m.GENERATOR_VAL_ACCURACY)
        if len(x):
            ax.plot(x, y, color=colour, label=f"{run.label}: validation accuracy")
        x, y = run.series(m.RELABEL_ACCURACY)
        if len(x):
            ax.plot(x, y, color=colour, linestyle="--", label=f"{run.label}: relabel accuracy")
    ax.set(xlabel="environment frames", ylabel="exact-match accuracy", ylim=(-0.02, 1.02),
           title="Instruction generator (solid: validation, dashed: relabels vs ground truth)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return fig


def replay_figure(runs: list[Run]):
    """One panel per run with replay data: the replay's share of each origin over frames, stacked."""
    plt = pyplot()
    with_data = [(run, *replay_fractions(run)) for run in runs]
    with_data = [d for d in with_data if len(d[1])] or [(runs[0], np.empty(0), np.empty((4, 0)))]
    n = len(with_data)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.5 * rows), squeeze=False, sharey=True)
    for ax, (run, x, fractions) in zip(axes.flat, with_data):
        if len(x):
            ax.stackplot(x, fractions, labels=[label for _, label, _ in REPLAY_KEYS],
                         colors=[c for _, _, c in REPLAY_KEYS], alpha=0.85)
        else:
            ax.text(0.5, 0.5, "no replay composition recorded", ha="center", va="center",
                    transform=ax.transAxes)
        ax.set(title=run.label, xlabel="environment frames", ylim=(0, 1))
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes[0][0].set_ylabel("fraction of replay")
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        # Below the panels, so it never hides data; bbox_inches="tight" keeps it in the file.
        fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(labels),
                   fontsize="small")
    fig.suptitle("Replay composition by origin")
    return fig


# (column, metric key, digits): a run's curve, one row per greedy evaluation
CURVE_COLUMNS = (("frames", m.FRAMES, 0), ("minutes", m.ELAPSED_S, 1), ("updates_per_frame", None, 4),
                 ("exploring_success", m.SUCCESS_TRAIN, 3), ("greedy_train", m.SUCCESS_EVAL_TRAIN, 3),
                 ("greedy_train_se", m.SUCCESS_EVAL_TRAIN + m.SE_SUFFIX, 3),
                 ("greedy_heldout", m.SUCCESS_EVAL_HELDOUT, 3),
                 ("greedy_heldout_se", m.SUCCESS_EVAL_HELDOUT + m.SE_SUFFIX, 3),
                 ("dataset", m.RELABEL_DATASET_SIZE, 0), ("gate_open", m.RELABEL_GATE_OPEN, 0),
                 ("generator_val", m.GENERATOR_VAL_ACCURACY, 3), ("relabel_accuracy_window", m.RELABEL_ACCURACY, 3),
                 ("relabelled_episodes", m.RELABELLED_EPISODES, 0), ("contradicting", m.RELABEL_CONTRADICTING, 0),
                 # empty unless the run kept a moving average of its weights (dqn.average_tau > 0)
                 ("greedy_train_averaged", m.SUCCESS_EVAL_TRAIN_AVERAGED, 3),
                 ("greedy_heldout_averaged", m.SUCCESS_EVAL_HELDOUT_AVERAGED, 3),
                 # greedy episodes that ended in a cycle (learning/episode_ends.py); empty in older runs
                 ("cycling_train", m.CYCLING_EVAL_TRAIN, 3), ("cycling_heldout", m.CYCLING_EVAL_HELDOUT, 3))


def curve_rows(run: Run) -> list[dict[str, str]]:
    """The run's record at each greedy evaluation (Run.evaluations: each once, the first record that
    carried it), and its last record, as text cells."""
    records = [e.record for e in run.evaluations()]
    if run.records and not any(r is run.records[-1] for r in records):
        records.append(run.records[-1])
    rows = []
    for r in records:
        row = {}
        for column, key, digits in CURVE_COLUMNS:
            value = r.get(key) if key else (r.get(m.UPDATES, 0) / r[m.FRAMES] if is_number(r.get(m.FRAMES)) and r[m.FRAMES] else None)
            if isinstance(value, bool):  # the gate: 1 open, 0 closed
                value = int(value)
            if key == m.ELAPSED_S and is_number(value):
                value = value / 60
            row[column] = "" if not is_number(value) else f"{float(value):.{digits}f}"
        rows.append(row)
    return rows


def write_table(run: Run, out: Path) -> Path:
    rows = curve_rows(run)
    path = out / f"{run.path.name}.csv"
    header = [c for c, _, _ in CURVE_COLUMNS]
    path.write_text("\n".join([",".join(header)] + [",".join(row[c] for c in header) for row in rows]) + "\n")
    print(f"\n{run.label} ({run.path}):\n| {' | '.join(header)} |\n|{' --- |' * len(header)}")
    for row in rows:
        print(f"| {' | '.join(row[c] or '-' for c in header)} |")
    return path


def _save(fig, out: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser("higher-plot", description="Plot the curves of one or more runs.",
                                     formatter_class=DefaultsHelp)
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories (or a folder of runs)")
    parser.add_argument("--out", default="plots", help="where the PNG files go")
    parser.add_argument("--table", action="store_true",
                        help="also write each run's curve at its evaluations as OUT/NAME.csv and print it")
    args = parser.parse_args(argv)
    try:
        runs = find_runs(args.runs)
    except NoRun as e:
        print(e, file=sys.stderr)
        return 2
    try:
        pyplot()
    except ImportError:
        print("higher-plot: matplotlib is missing; pip install 'higher-dist[plot]'", file=sys.stderr)
        return 2
    out = Path(args.out)
    try:
        ensure_folder(out, "--out")
    except ValueError as e:
        print(f"higher-plot: error: {e}", file=sys.stderr)
        return 2

    greedy = all(success_key(run) == m.SUCCESS_EVAL_TRAIN for run in runs)
    title = ("Greedy success on training goals" if greedy
             else "Success on training goals (greedy where evaluated, else while exploring)")
    written = [_save(success_figure(runs, success_key, title), out / "success_rate.png")]
    heldout = [run for run in runs if run.has(m.SUCCESS_EVAL_HELDOUT)]
    if heldout:
        written.append(_save(success_figure(heldout, lambda run: m.SUCCESS_EVAL_HELDOUT,
                                            "Greedy success on held-out goals"), out / "success_rate_heldout.png"))
    averaged = [run for run in runs if run.has(m.SUCCESS_EVAL_TRAIN_AVERAGED)]
    if averaged:
        written.append(_save(success_figure(averaged, lambda run: m.SUCCESS_EVAL_TRAIN_AVERAGED,
                                            "Greedy success of the averaged weights on training goals"),
                             out / "success_rate_averaged.png"))
    generator_runs = [run for run in runs if run.has(m.GENERATOR_VAL_ACCURACY) or run.has(m.RELABEL_ACCURACY)]
    if generator_runs:
        written.append(_save(generator_figure(generator_runs), out / "generator_accuracy.png"))
    else:
        print("higher-plot: no generator data in these runs; skipped generator_accuracy.png")
    written.append(_save(replay_figure(runs), out / "replay_composition.png"))
    if args.table:
        written += [write_table(run, out) for run in runs]
    for path in written:
        print(path)
    return 0
