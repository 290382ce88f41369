"""The paper's figures from a plan's folder: mean and a band of one standard deviation over seeds.

A method is a plan variant (`her`, `noisy-her-p0.5`, ...); its seeds are interpolated onto the frames
they all cover. The headline curves are the greedy evaluations (`success_rate_eval_train`,
`success_rate_eval_heldout`); a run without any evaluation falls back to its training success and the
legend says so. A BabyAI level has no held-out goals: its plans draw no held-out figure. Small PNGs (6x4 inches at 80 dpi) go to DIR/figures.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from higher_dist import metrics as m
from higher_dist.analysis.drawing import pyplot
from higher_dist.config import is_babyai_world
from higher_dist.analysis.runs import GRID_POINTS, REPLAY_KEYS, NoRun, Run, is_number, load_run, replay_fractions
from higher_dist.reproduce import replay_claims
from higher_dist.reproduce.plan import GENERATOR_PAIRS, NOISE_LEVELS, PAPER_GENERATOR_EXACT, TRIGGER_PAIRS, Plan, seeds_text

EVAL_TRAIN, EVAL_HELDOUT = m.SUCCESS_EVAL_TRAIN, m.SUCCESS_EVAL_HELDOUT
EVALUATIONS = (EVAL_TRAIN, EVAL_HELDOUT, m.SUCCESS_EVAL_TRAIN_AVERAGED, m.SUCCESS_EVAL_HELDOUT_AVERAGED)
MAIN_VARIANTS = ("dqn", "her", "higher", "reward")
DPI, SIZE = 80, (6.0, 4.0)
FINAL_EVALS = 3  # a run's end point: the mean of its last three greedy evaluations (docs/results.md)


@dataclass
class Group:
    variant: str
    label: str
    runs: list[Run] = field(default_factory=list)

    def key(self, wanted: str) -> str:
        """`wanted` when a run has it, else the training success (a run too short to be evaluated)."""
        return wanted if any(r.has(wanted) for r in self.runs) else m.SUCCESS_TRAIN


def has_heldout(plan: Plan) -> bool:
    """Whether the plan's world keeps goals out of training (FetchAttr does; a BabyAI level does not)."""
    return not is_babyai_world(plan.settings.get("world", "paper"))


def load_groups(plan: Plan) -> dict[str, Group]:
    groups: dict[str, Group] = {}
    for spec in plan.runs:
        if spec.kind != "cluster":
            continue
        try:
            run = load_run(plan.path(spec))
        except NoRun:
            continue
        run.seed = spec.seed
        groups.setdefault(spec.variant, Group(spec.variant, spec.label)).runs.append(run)
    return groups


def generator_results(plan: Plan) -> dict[int, list[dict]]:
    """pairs -> the result.json of each seed's generator run."""
    out: dict[int, list[dict]] = {}
    for spec in plan.runs:
        path = plan.path(spec) / "result.json"
        if spec.kind == "generator" and path.exists():
            out.setdefault(spec.pairs, []).append(json.loads(path.read_text()))
    return dict(sorted(out.items()))


def std_band(curves: list[tuple[np.ndarray, np.ndarray]]):
    """(grid, mean, std) over the frames every curve covers; a single curve gets a zero band."""
    curves = [(x, y) for x, y in curves if len(x) > 0]
    if not curves:
        return None
    start, stop = max(x[0] for x, _ in curves), min(x[-1] for x, _ in curves)
    if stop < start:
        return None
    grid = np.linspace(start, stop, GRID_POINTS) if stop > start else np.array([start])
    ys = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, ys.mean(axis=0), ys.std(axis=0)


def final(run: Run, key: str) -> float | None:
    """A run's end point for `key`. For a greedy evaluation: the mean of the run's last FINAL_EVALS
    evaluations (Run.evaluations: each once), as one evaluation swings 5-10 points late in a run;
    otherwise the latest value."""
    evals = [v for v in (e.value(key) for e in run.evaluations()) if v is not None] if key in EVALUATIONS else []
    if evals:
        return float(np.mean(evals[-FINAL_EVALS:]))
    _, y = run.series(key)
    return float(y[-1]) if len(y) else None


def final_stats(group: Group | None, key: str) -> dict | None:
    """mean, std, seeds, frames (the fewest any seed reached) and the per-seed values of the latest values
    of `key`."""
    if group is None:
        return None
    values = [v for v in (final(r, key) for r in group.runs) if v is not None]
    if not values:
        return None
    frames = min(int(max((rec.get(m.FRAMES) or 0) for rec in r.records)) for r in group.runs)
    return {"mean": float(np.mean(values)), "std": float(np.std(values)), "n": len(values), "frames": frames,
            "values": [float(v) for v in values]}


def _figure(title: str, xlabel: str, ylabel: str):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=SIZE)
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel, ylim=(-0.02, 1.02))
    ax.grid(alpha=0.3)
    return fig, ax


def _save(fig, ax, path: Path, legend_below: bool = False) -> Path:
    """`legend_below`: under the axes, for a figure whose marks would hide behind a legend inside."""
    import matplotlib.pyplot as plt

    if ax.get_legend_handles_labels()[0]:
        if legend_below:
            ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=2, fontsize="x-small")
        else:
            ax.legend(loc="best", fontsize="x-small")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def _curves(ax, groups: list[Group], wanted: str) -> bool:
    drawn = False
    for i, group in enumerate(groups):
        key = group.key(wanted)
        band = std_band([r.series(key) for r in group.runs])
        if band is None:
            continue
        grid, mean, std = band
        note = "" if key == wanted else " (training success: no evaluation yet)"
        ax.plot(grid, mean, color=f"C{i}", label=f"{group.label}, {seeds_text(len(group.runs))}{note}")
        ax.fill_between(grid, mean - std, mean + std, color=f"C{i}", alpha=0.2, linewidth=0)
        drawn = True
    return drawn


def draw_all(plan: Plan) -> dict[str, Path]:
    """Every figure the folder has data for; name -> path."""
    out = plan.out / "figures"
    out.mkdir(parents=True, exist_ok=True)
    groups = load_groups(plan)
    written: dict[str, Path] = {}
    main = [groups[v] for v in MAIN_VARIANTS if v in groups]
    goal_sets = [("success_train", EVAL_TRAIN, "Greedy success, training goals")]
    if has_heldout(plan):
        goal_sets.append(("success_heldout", EVAL_HELDOUT, "Greedy success, held-out goals"))
    for name, key, title in goal_sets:
        fig, ax = _figure(title, "environment frames", "success rate")
        if _curves(ax, main, key):
            written[name] = _save(fig, ax, out / f"{name}.png")
        else:
            pyplot().close(fig)
    generator_groups = [g for g in groups.values() if g.variant.startswith("higher")
                        and any(r.has(m.GENERATOR_VAL_ACCURACY) for r in g.runs)]
    if generator_groups:
        fig, ax = _figure("HIGhER's generator: validation exact match", "environment frames", "exact match")
        _curves(ax, generator_groups, m.GENERATOR_VAL_ACCURACY)
        written["generator_accuracy"] = _save(fig, ax, out / "generator_accuracy.png")
    if main:
        written["replay_composition"] = replay_figure(main, out / "replay_composition.png")
    if "higher" in groups:
        written["replay_vs_paper"] = replay_vs_paper_figure(groups["higher"], out / "replay_vs_paper.png")
    if any(f"noisy-her-p{p}" in groups for p in NOISE_LEVELS):
        written["noise"] = noise_figure(groups, out / "noise.png")
        noisy = [groups[v] for v in ["dqn", "her", *(f"noisy-her-p{p}" for p in NOISE_LEVELS)] if v in groups]
        fig, ax = _figure("DQN+HER with attribute noise p, over training", "environment frames",
                          "greedy success, training goals")
        _curves(ax, noisy, EVAL_TRAIN)
        written["noise_curves"] = _save(fig, ax, out / "noise_curves.png")
    triggers = [groups[f"higher-trigger{n}"] for n in TRIGGER_PAIRS if f"higher-trigger{n}" in groups]
    if triggers:
        fig, ax = _figure("Generator switched on after N pairs", "environment frames", "greedy success, training goals")
        _curves(ax, triggers, EVAL_TRAIN)
        written["trigger"] = _save(fig, ax, out / "trigger.png")
    gen = generator_results(plan)
    if gen:
        written["generator_pairs"] = generator_figure(gen, out / "generator_pairs.png")
    return written


def replay_figure(groups: list[Group], path: Path) -> Path:
    """Mean replay composition by origin over seeds, one panel per method."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(groups), figsize=(2.6 * len(groups) + 0.6, 3.0), squeeze=False, sharey=True)
    for ax, group in zip(axes[0], groups):
        data = [replay_fractions(r) for r in group.runs]
        data = [(x, f) for x, f in data if len(x)]
        if data:
            start, stop = max(x[0] for x, _ in data), min(x[-1] for x, _ in data)
            grid = np.linspace(start, stop, GRID_POINTS) if stop > start else np.array([start])
            mean = np.mean([[np.interp(grid, x, row) for row in f] for x, f in data], axis=0)
            ax.stackplot(grid, mean, labels=[label for _, label, _ in REPLAY_KEYS],
                         colors=[c for _, _, c in REPLAY_KEYS], alpha=0.85)
        ax.set(title=group.label, xlabel="frames", ylim=(0, 1))
        ax.tick_params(labelsize="x-small")
    axes[0][0].set_ylabel("fraction of replay")
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize="x-small")
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def replay_vs_paper_figure(group: Group, path: Path) -> Path:
    """Each origin's share over frames for one method (mean and one std over seeds), the paper's figures
    as stars where the paper places them (its end, 5M frames, drawn at our last frame)."""
    fig, ax = _figure(f"{group.label}: the replay by origin, {seeds_text(len(group.runs))}", "environment frames",
                      "share of the replay")
    data = [d for d in map(replay_fractions, group.runs) if len(d[0])]
    bands = {name: std_band([(x, share(f)) for x, f in data]) for name, share in replay_claims.SHARES.items()}
    for i, (name, band) in enumerate(bands.items()):
        if band is not None:
            grid, mean, std = band
            ax.plot(grid, mean, color=f"C{i}", label=name)
            ax.fill_between(grid, mean - std, mean + std, color=f"C{i}", alpha=0.2, linewidth=0)
    stats = replay_claims.group_measures(group.runs)
    if stats and bands["negative"] is not None:
        grid = bands["negative"][0]
        paper = replay_claims.PAPER
        marks = (("negative", grid[0], paper["negative_start"]),
                 ("relabelled", stats["peak_frames"], paper["relabelled_peak"]),
                 ("relabelled", grid[-1], paper["relabelled_end"]), ("positive", grid[-1], paper["positive_end"]))
        for name, x, y in marks:
            ax.plot([x], [y], marker="*", markersize=11, color=f"C{list(bands).index(name)}", linestyle="none")
        ax.axhline(paper["timeout_mean"], color=f"C{list(bands).index('time-outs')}", linestyle=":", linewidth=1)
        ax.plot([], [], marker="*", color="grey", linestyle="none",
                label="the paper (stars; its 5M end at our last frame; dotted: its mean time-outs)")
    return _save(fig, ax, path, legend_below=True)


def noise_figure(groups: dict[str, Group], path: Path) -> Path:
    fig, ax = _figure("DQN+HER with attribute noise p", "noise p", "final greedy success, training goals")
    ps, means, stds = [], [], []
    for p, variant in [(0.0, "her")] + [(p, f"noisy-her-p{p}") for p in NOISE_LEVELS]:
        stats = final_stats(groups.get(variant), groups[variant].key(EVAL_TRAIN) if variant in groups else EVAL_TRAIN)
        if stats:
            ps.append(p), means.append(stats["mean"]), stds.append(stats["std"])
    ax.errorbar(ps, means, yerr=stds, marker="o", capsize=3, label="DQN+HER noisy (mean, 1 std)")
    dqn = final_stats(groups.get("dqn"), groups["dqn"].key(EVAL_TRAIN) if "dqn" in groups else EVAL_TRAIN)
    if dqn:
        ax.axhline(dqn["mean"], color="C3", linestyle="--", label="DQN")
        ax.axhspan(dqn["mean"] - dqn["std"], dqn["mean"] + dqn["std"], color="C3", alpha=0.15)
    ax.set_xlim(-0.05, 0.85)
    return _save(fig, ax, path)


def generator_figure(results: dict[int, list[dict]], path: Path) -> Path:
    fig, ax = _figure("Generator from expert pairs", "expert training pairs", "exact match")
    pairs = list(results)
    for i, (key, label) in enumerate((("seen_exact_match", "seen goals"), ("unseen_exact_match", "unseen goals"))):
        values = [[r[key] for r in results[n] if is_number(r.get(key))] for n in pairs]
        ax.errorbar(pairs, [np.mean(v) for v in values], yerr=[np.std(v) for v in values], marker="o",
                    capsize=3, color=f"C{i}", label=label)
    ax.plot(list(PAPER_GENERATOR_EXACT), list(PAPER_GENERATOR_EXACT.values()), "k*", markersize=11,
            linestyle="none", label="the paper")
    ax.set_xticks(list(GENERATOR_PAIRS))
    return _save(fig, ax, path, legend_below=True)
