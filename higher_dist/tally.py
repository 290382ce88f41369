"""`higher-render RUN_DIR --tally N`: how N greedy episodes of a run's latest checkpoint end, and why
the failures fail: success, wrong outcome, cycling or searching (learning/episode_ends.py says what each
is; the learner's evaluation reports the cycling share beside success as it goes).

On a BabyAI level the table has a row per location phrase the missions use ("on your left", ..., and
"none" for missions that name no location), since those missions ask the agent to remember where it
started; on FetchAttr a row per mission prefix, which names nothing. The episodes' layouts and goals
are the run's own evaluation goals at the checkpoint's frame count (Seeds.evaluation_env_seeds), so the
online and the averaged weights are scored on the same episodes, and the success column is the run's
evaluation at that count. `--epsilon` acts epsilon-greedily instead: then "cycling" only says the views
repeated.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from higher_dist.learning.acting import first_episodes
from higher_dist.learning.episode import Episode
from higher_dist.learning.episode_ends import KINDS, end_of
from higher_dist.learning.seeds import Seeds
from higher_dist.world.babyai_language import LOC_PHRASES
from higher_dist.world.spec import WorldSpec


def mission_group(spec: WorldSpec, ep: Episode) -> str:
    """The location phrase a BabyAI mission names ("none" if it names none); on FetchAttr the mission's
    prefix ("go fetch a", ...), which names nothing: an agent that understands the missions succeeds as
    often under each, and one trained on relabels of a single phrasing may not."""
    if spec.family != "babyai":
        return spec.language.prefix(ep.mission) or "none"
    text = spec.language.decode(ep.mission)
    return next((phrase for phrase in LOC_PHRASES if phrase in text), "none")


def play(cfg, policy, episodes: int, frames: int, goal_set: str = "train", epsilon: float = 0.0) -> list[Episode]:
    """One episode per environment of a batch of `episodes`, played to its end by `policy` (greedy, or
    epsilon-greedy with `epsilon`), on the run's evaluation goals at `frames`."""
    env_seeds = Seeds(cfg.seed).evaluation_env_seeds(frames, episodes)
    rng = np.random.default_rng(env_seeds[0]) if epsilon > 0 else None
    return first_episodes(policy, cfg.world, cfg.network.frame_stack, goal_set, env_seeds, epsilon=epsilon, rng=rng)


@dataclass
class Tally:
    groups: dict  # group -> {kind: count}
    lengths: dict  # kind -> mean episode length in steps
    periods: dict  # cycle period -> episodes caught in a cycle of that period

    @classmethod
    def of(cls, spec: WorldSpec, episodes: list[Episode], stack: int) -> "Tally":
        groups: dict[str, dict[str, int]] = {}
        by_kind: dict[str, list[int]] = {kind: [] for kind in KINDS}
        periods: dict[int, int] = {}
        for ep in episodes:
            kind, period = end_of(ep, stack)
            if period:
                periods[period] = periods.get(period, 0) + 1
            counts = groups.setdefault(mission_group(spec, ep), dict.fromkeys(KINDS, 0))
            counts[kind] += 1
            by_kind[kind].append(ep.length)
        order = sorted(groups, key=lambda g: (g in ("all", "none"), g))  # named locations first, then the rest
        return cls({g: groups[g] for g in order}, {k: float(np.mean(v)) if v else float("nan")
                                                    for k, v in by_kind.items()}, dict(sorted(periods.items())))

    def total(self) -> dict[str, int]:
        return {kind: sum(c[kind] for c in self.groups.values()) for kind in KINDS}

    def markdown(self) -> str:
        """A table: episodes and the share of each kind, per mission group and over all of them."""
        rows = list(self.groups.items())
        if len(rows) > 1:
            rows.append(("every mission", self.total()))
        lines = ["| missions | episodes | " + " | ".join(KINDS) + " |", "| --- | --- |" + " --- |" * len(KINDS)]
        for group, counts in rows:
            n = sum(counts.values())
            lines.append(f"| {group} | {n} | " + " | ".join(f"{100 * counts[k] / n:.1f}%" for k in KINDS) + " |")
        lengths = ", ".join(f"{k} {v:.1f}" for k, v in self.lengths.items() if v == v)
        lines.append("")
        lines.append(f"mean length in steps: {lengths}")
        if self.periods:
            periods = ", ".join(f"{p}: {n}" for p, n in self.periods.items())
            lines.append("cycles by period (steps until the input repeats; 1: an action that changes nothing, such "
                         f"as a step into a wall; 2: back and forth; 4: a turn on the spot): {periods}")
        return "\n".join(lines)
