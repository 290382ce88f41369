"""`higher-render RUN_DIR --tally N`: how N greedy episodes of a run's latest checkpoint end, and why
the failures fail.

Every episode ends one of four ways:
- success: the mission's outcome;
- wrong outcome: it achieved something else (FetchAttr: picked a wrong object; BabyAI: an outcome of
  the level's kind that is not the mission's) and got nothing for it;
- cycling: it achieved nothing, and before the time-out its input repeated: the last `frame_stack`
  views it acted on equal the ones P steps earlier (P <= MAX_PERIOD). The world does not change while
  nothing is achieved and the greedy policy is a function of its input and the mission, so from there
  it would repeat the same P actions forever (typically a turn on the spot);
- searching: it achieved nothing, and its input never repeated like that: it was still moving about.

Relabelling can only help the first two kinds of failure to the extent that something was achieved:
a wrong outcome is what HER and HIGhER relabel, a cycle or a search gives them nothing to describe.

On a BabyAI level the table has a row per location phrase the missions use ("on your left", ..., and
"none" for missions that name no location), since those missions ask the agent to remember where it
started. The episodes' layouts and goals are the run's own evaluation goals at the checkpoint's frame
count (Seeds.evaluation_env_seeds), so the online and the averaged weights are scored on the same
episodes. `--epsilon` acts epsilon-greedily instead: then "cycling" only says the views repeated.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from higher_dist.learning.acting import EpisodeCollector
from higher_dist.learning.episode import Episode
from higher_dist.learning.seeds import Seeds
from higher_dist.world.spec import SUCCESS, WorldSpec

MAX_PERIOD = 16  # longest cycle looked for: 4 turns make a full turn on the spot, 16 steps cover any small loop
KINDS = ("success", "wrong outcome", "cycling", "searching")


def cycle_period(frames: np.ndarray, stack: int, max_period: int = MAX_PERIOD) -> int:
    """The shortest P in [1, max_period] for which the last `stack` views an agent acted on equal the
    `stack` views P steps before them; 0 when none does.

    `frames` (T+1, V, V, C): an episode's views, the last one after its last action (not acted on)."""
    acted = np.asarray(frames)[:-1]
    steps = len(acted)
    for period in range(1, max_period + 1):
        if period + stack > steps:
            break
        if np.array_equal(acted[steps - stack:], acted[steps - stack - period:steps - period]):
            return period
    return 0


def classify(ep: Episode, stack: int) -> str:
    """One of KINDS for an episode played to its end."""
    if ep.outcome == SUCCESS:
        return "success"
    if ep.pick_step is not None and ep.pick_step >= 0:
        return "wrong outcome"
    return "cycling" if cycle_period(ep.frames, stack) else "searching"


def mission_group(spec: WorldSpec, ep: Episode) -> str:
    """The location phrase a BabyAI mission names ("none" if it names none); "all" on FetchAttr."""
    if spec.family != "babyai":
        return "all"
    from higher_dist.world.babyai_language import LOC_PHRASES

    text = spec.language.decode(ep.mission)
    return next((phrase for phrase in LOC_PHRASES if phrase in text), "none")


def play(cfg, policy, episodes: int, frames: int, goal_set: str = "train", epsilon: float = 0.0) -> list[Episode]:
    """One episode per environment of a batch of `episodes`, played to its end by `policy` (greedy, or
    epsilon-greedy with `epsilon`), on the run's evaluation goals at `frames`."""
    spec = WorldSpec.of(cfg.world)
    env_seeds = Seeds(cfg.seed).evaluation_env_seeds(frames, episodes)
    collector = EpisodeCollector(cfg.world, episodes, cfg.network.frame_stack, goal_set=goal_set, env_seeds=env_seeds)
    rng = np.random.default_rng(env_seeds[0])
    done: list[Episode | None] = [None] * episodes
    while any(ep is None for ep in done):
        obs, mission = collector.observation()
        actions = policy(obs, mission).argmax(axis=1)
        if epsilon > 0:
            explore = rng.random(episodes) < epsilon
            actions = np.where(explore, rng.integers(spec.n_actions, size=episodes), actions)
        finished = collector.step(actions)
        # A finished environment starts its next episode at once (step 0); only its first one counts.
        for i, ep in zip(np.flatnonzero(collector.world.steps == 0), finished):
            if done[i] is None:
                done[i] = ep
    return done


@dataclass
class Tally:
    groups: dict  # group -> {kind: count}
    lengths: dict  # kind -> mean episode length in steps
    periods: dict  # cycle period -> episodes caught in a cycle of that period
    stack: int

    @classmethod
    def of(cls, spec: WorldSpec, episodes: list[Episode], stack: int) -> "Tally":
        groups: dict[str, dict[str, int]] = {}
        by_kind: dict[str, list[int]] = {kind: [] for kind in KINDS}
        periods: dict[int, int] = {}
        for ep in episodes:
            kind = classify(ep, stack)
            if kind == "cycling":
                period = cycle_period(ep.frames, stack)
                periods[period] = periods.get(period, 0) + 1
            counts = groups.setdefault(mission_group(spec, ep), dict.fromkeys(KINDS, 0))
            counts[kind] += 1
            by_kind[kind].append(ep.length)
        order = sorted(groups, key=lambda g: (g in ("all", "none"), g))  # named locations first, then the rest
        return cls({g: groups[g] for g in order}, {k: float(np.mean(v)) if v else float("nan")
                                                    for k, v in by_kind.items()}, dict(sorted(periods.items())), stack)

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
            lines.append("cycles by period (steps until the input repeats; 1: an action that changes nothing, such "
                         "as a step into a wall; 2: back and forth; 4: a turn on the spot): " + ", ".join(f"{p}: {n}" for p, n in self.periods.items()))
        return "\n".join(lines)
