"""Hindsight relabelling strategies: what a failed episode is stored again under.

The paper's methods differ only here (config_presets.PRESET_RELABEL gives each preset its strategy):
- `none`    (DQN, DQN+reward): nothing is relabelled;
- `expert`  (DQN+HER): the picked object, described from ground truth (the expert reads it by design);
- `noisy`   (DQN+HER noisy): the same with each attribute swapped to another value with probability p;
- `learned` (DQN+HIGhER): the instruction generator describes the view before the pick; it is trained
  on successful episodes only, and used only once its gate is open. With `relabel.words=expert` the
  generator still trains and gates, but the relabels carry the expert's words: an ablation that keeps
  HIGhER's cold start and removes its generator's mistakes.

Every strategy relabels copies of failed episodes that achieved something: successes already carry their
reward, episodes that achieved nothing have nothing to describe, and relabelled copies are never relabelled
again. On FetchAttr a failed pick ends the episode (a wrong pick, its one outcome); on a BabyAI level the
agent goes on reaching, opening or picking until the time-out, and the episode records each distinct outcome.
Each outcome may give a copy that describes it and ends there, with the reward the level gives a success on
that step: up to `relabel.max_per_episode` copies per episode (a random choice when it achieved more). The
missions are the world's own language (WorldSpec.language). The learner counts only original episodes'
frames, so copies never buy updates. Each relabel is scored against the achieved object for the dashboard; that score is computed after the
relabels are made and is never fed back into training. `relabel_accuracy` is over the last
`RECENT_RELABELS` relabels (a window, so it follows the generator as it improves);
`relabel_accuracy_total` is since the start of the run.
"""
from __future__ import annotations

import itertools
from collections import deque
from typing import Any

import numpy as np

from higher_dist import metrics as m
from higher_dist.config import RELABEL_STRATEGIES, Config, GeneratorConfig, RelabelConfig
from higher_dist.learning.episode import SUCCESS, Episode, Withheld, episodes_from_state, episodes_state
from higher_dist.learning.hindsight.generator import GeneratorTrainer
from higher_dist.learning.hindsight.generator_data import generator_inputs
from higher_dist.learning.seeds import RelabelerSeeds
from higher_dist.world.language import noisy_attrs
from higher_dist.world.objects import ObjectSpace
from higher_dist.world.spec import DEFAULT_SPEC, WorldSpec

RECENT_RELABELS = 1000  # window of the reported relabel accuracy
# Held episodes relabelled per call once the gate opens: a few thousand at once would make one huge
# message and one long pause of the relabeler; this many beside each batch clears them within seconds.
HELD_RELEASE = 128


def relabel_candidates(episodes: list[Episode]) -> list[Episode]:
    """The episodes a strategy may relabel: original failures that achieved an outcome."""
    return [ep for ep in episodes if ep.outcome != SUCCESS and ep.pick_step >= 0 and not ep.relabelled]


class Outcome:
    """One achieved outcome of a candidate episode: where a copy describing it would end. What it achieved
    (`attrs`, ground truth) is read only when asked for: by the expert, and by the score."""
    __slots__ = ("episode", "index", "step")

    def __init__(self, episode: Episode, index: int, step: int):
        self.episode, self.index, self.step = episode, index, step

    @property
    def attrs(self) -> np.ndarray:
        return np.asarray(self.episode.outcome_attrs(self.index), np.int64)


class RelabelStrategy:
    """Base class and the `none` strategy: observes nothing, relabels nothing."""

    name = "none"

    def __init__(self, seed: int | RelabelerSeeds = 0, spec: WorldSpec = DEFAULT_SPEC,
                 max_per_episode: int = RelabelConfig.max_per_episode):
        """`seed`: the relabeler's streams (Seeds.relabeler), or a run seed standing for its streams."""
        self.rng = np.random.default_rng(RelabelerSeeds.of(seed).draws)
        self.spec, self.language = spec, spec.language
        self.max_per_episode = int(max_per_episode)
        self.considered = 0  # wrong-pick episodes offered for relabelling
        self.relabelled = 0  # copies returned
        self.correct = 0  # copies whose instruction describes the picked object (metrics only)
        self.recent_correct: deque[bool] = deque(maxlen=RECENT_RELABELS)
        self.contradicting = 0  # relabels dropped because they named the failed goal

    def observe(self, episodes: list[Episode]) -> None:
        """Learn from a batch of finished episodes (only the learned strategy does)."""

    def relabel(self, episodes: list[Episode]) -> list[Episode]:
        """Relabelled copies of the wrong-pick episodes among `episodes` (the originals are untouched)."""
        self.considered += len(relabel_candidates(episodes))
        return []

    def withheld(self, episodes: list[Episode]) -> list[Episode]:
        """The originals among `episodes` to keep out of the replay (only the learned strategy keeps any)."""
        return []

    def _outcomes(self, candidates: list[Episode]) -> list[Outcome]:
        """The outcomes to describe: every one of each candidate's, or a random `max_per_episode` of them."""
        chosen = []
        for ep in candidates:
            steps = ep.outcome_steps()
            picks = range(len(steps))
            if len(steps) > self.max_per_episode:
                picks = sorted(self.rng.choice(len(steps), self.max_per_episode, replace=False).tolist())
            chosen += [Outcome(ep, k, steps[k]) for k in picks]
        return chosen

    def _copies(self, outcomes: list[Outcome], missions) -> list[Episode]:
        """The relabelled copies: each ends at its outcome, rewarded as the world rewards a success there."""
        return [o.episode.relabel(t, float(self.spec.pick_reward(o.step + 1)), outcome=o.index)
                for o, t in zip(outcomes, missions)]

    def train(self, budget_steps: int | None = None) -> dict[str, float]:
        """Spend up to `budget_steps` gradient steps on the generator (only the learned strategy does)."""
        return {}

    @property
    def generator_accuracy(self) -> float | None:
        """The generator's latest validation exact match; None without a generator or a measurement."""
        return None

    @property
    def gate_open(self) -> bool | None:
        """Whether the generator's gate lets relabels through; None without a generator."""
        return None

    def _not_contradicting(self, candidates: list[Outcome], attrs: np.ndarray) -> np.ndarray:
        """Indices of the relabels that do not name the goal the episode just failed. Such a copy would
        store the same transitions with reward 1 beside the original with reward 0; it is dropped and
        counted as `contradicting`. Compared with the mission the agent followed, not with ground truth."""
        if not candidates:
            return np.zeros(0, np.int64)
        goals, _ = self.language.parse_many(np.stack([o.episode.mission for o in candidates]))
        keep = ~(np.asarray(attrs, np.int64) == goals).all(axis=1)
        self.contradicting += int((~keep).sum())
        return np.flatnonzero(keep)

    def _score(self, originals: list[Outcome], new_attrs: np.ndarray) -> None:
        """Count relabels whose described object is the one achieved. The only reader of the achieved
        objects in a learned relabel, and it runs after the relabels exist: a score, never an input."""
        if not originals:
            return
        picked = np.stack([o.attrs for o in originals])
        right = self.language.satisfies(np.asarray(new_attrs, np.int64), picked)
        self.correct += int(right.sum())
        self.recent_correct.extend(right.tolist())
        self.relabelled += len(originals)

    def metrics(self) -> dict[str, Any]:
        """Every key of `metrics.RELABEL_KEYS`; None where this strategy has no such thing (no generator)."""
        return {
            **dict.fromkeys(m.RELABEL_KEYS),
            m.RELABEL_STRATEGY: self.name,
            m.RELABEL_CONSIDERED: self.considered,
            m.RELABELS_MADE: self.relabelled,
            # None until something was relabelled: "no data", not "always wrong".
            m.RELABEL_ACCURACY: (sum(self.recent_correct) / len(self.recent_correct)
                                 if self.recent_correct else None),
            m.RELABEL_ACCURACY_TOTAL: self.correct / self.relabelled if self.relabelled else None,
            m.RELABEL_CONTRADICTING: self.contradicting,
        }

    def state_dict(self) -> dict[str, Any]:
        return {"name": self.name, "rng": self.rng.bit_generator.state, "considered": self.considered,
                "relabelled": self.relabelled, "correct": self.correct, "contradicting": self.contradicting,
                "recent_correct": list(self.recent_correct)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["name"] != self.name:
            raise ValueError(f"relabeler: checkpoint is for strategy {state['name']!r}, not {self.name!r}")
        self.rng.bit_generator.state = state["rng"]
        self.considered, self.relabelled, self.correct = (
            int(state["considered"]), int(state["relabelled"]), int(state["correct"]))
        self.recent_correct.clear()
        self.recent_correct.extend(bool(x) for x in state.get("recent_correct", []))
        self.contradicting = int(state.get("contradicting", 0))


class ExpertRelabel(RelabelStrategy):
    """HER with an expert: describe the object actually achieved (FetchAttr: with a random prefix and word order;
    a BabyAI level whose missions name locations: with one of the locations the object is in)."""

    name = "expert"

    def _attrs_for(self, picked: np.ndarray) -> np.ndarray:
        return picked

    def relabel(self, episodes: list[Episode]) -> list[Episode]:
        candidates = relabel_candidates(episodes)
        self.considered += len(candidates)
        # An achieved outcome always names its object; the check guards malformed input.
        named = self.spec.picked_columns
        candidates = [o for o in self._outcomes(candidates) if np.all(o.attrs[:named] >= 0)]
        if not candidates:
            return []
        attrs = self._attrs_for(np.stack([o.attrs for o in candidates]))  # the expert reads the truth by design
        tokens = self.spec.expert_tokens(attrs, self.rng)
        described, _ = self.language.parse_many(tokens)  # what the sentences say
        keep = self._not_contradicting(candidates, described)
        candidates, described, tokens = [candidates[i] for i in keep], described[keep], tokens[keep]
        self._score(candidates, described)
        return self._copies(candidates, tokens)


class NoisyExpertRelabel(ExpertRelabel):
    """The expert with each of the 4 attributes swapped, with probability p, to another of the world's
    values (as the paper defines noisy HER: all four stay right with probability (1 - p)^4)."""

    name = "noisy"

    def __init__(self, space: ObjectSpace, p: float, seed: int | RelabelerSeeds = 0, spec: WorldSpec = DEFAULT_SPEC,
                 max_per_episode: int = RelabelConfig.max_per_episode):
        super().__init__(seed, spec, max_per_episode)
        self.space, self.p = space, float(p)

    def _attrs_for(self, picked: np.ndarray) -> np.ndarray:
        return np.asarray(noisy_attrs(picked, self.p, self.space, self.rng), np.int64)


class LearnedRelabel(RelabelStrategy):
    """HIGhER: the instruction generator describes the view that shows each chosen outcome (the view before
    a pick or an open, after a go-to's step: WorldSpec.outcome_view_offset).

    It reads `ep.frames` and the outcomes' steps only: never what was achieved or `ep.goal` (except
    `_score`, after the fact).
    While the gate is closed nothing is relabelled and the failures offered are counted as `gated_off`;
    the newest `relabel.held_while_gated` of them are kept and relabelled once it opens (the agent then
    learns from the frames it spent waiting for the gate too). With `relabel.withheld_while_gated` those
    failures are also kept out of the replay while the gate is shut, counted as `withheld`: the agent
    does not learn that its picks fail before a relabel can teach it what they achieved. An output that
    does not parse to an object of the language is dropped and counted as `unparseable`, one whose object fewer
    than `generator.min_agreement` of `generator.agreement_draws` drawn instructions name is dropped and
    counted as `unsure`, one that names the episode's own (failed) goal is dropped and counted as
    `contradicting`. With `words="expert"` the open gate lets through the expert's words instead of the
    generator's (the ablation reads the achieved object, as the expert does).
    """

    name = "learned"

    def __init__(self, cfg: GeneratorConfig, spec: WorldSpec = DEFAULT_SPEC, seed: int | RelabelerSeeds = 0,
                 device: str = "cpu", max_per_episode: int = RelabelConfig.max_per_episode,
                 held_while_gated: int = RelabelConfig.held_while_gated, words: str = RelabelConfig.words,
                 withheld_while_gated: bool = RelabelConfig.withheld_while_gated):
        super().__init__(seed, spec, max_per_episode)
        self.cfg, self.words, self.withhold = cfg, words, bool(withheld_while_gated)
        self.trainer = GeneratorTrainer(cfg, spec, seed, device=device)
        self.unparseable = 0
        self.unsure = 0  # parsed relabels dropped: too few of the generator's draws named their object
        self.gated_off = 0  # wrong picks offered while the gate was closed (the held ones among them)
        self.withheld_count = 0  # of those, the originals kept out of the replay
        self.held: deque[Episode] = deque(maxlen=int(held_while_gated))  # the newest of them, oldest first
        self._steps_since_eval = 0

    def observe(self, episodes: list[Episode]) -> None:
        self.trainer.observe_episodes(episodes)

    def withheld(self, episodes: list[Episode]) -> list[Episode]:
        if not self.withhold or self.trainer.gate_open:
            return []
        kept_out = relabel_candidates(episodes)
        self.withheld_count += len(kept_out)
        return kept_out

    def relabel(self, episodes: list[Episode]) -> list[Episode]:
        candidates = relabel_candidates(episodes)
        self.considered += len(candidates)
        if not self.trainer.gate_open:
            self.gated_off += len(candidates)
            # Kept as they are: the collector and the wire's unpacking give each episode its own arrays.
            self.held.extend(candidates)
            return []
        released = [self.held.popleft() for _ in range(min(HELD_RELEASE, len(self.held)))]
        candidates = released + candidates
        if not candidates:
            return []
        candidates = self._outcomes(candidates)
        if self.words == "expert":  # the ablation: the expert reads what was achieved; no view is built
            tokens = self.spec.expert_tokens(np.stack([o.attrs for o in candidates]), self.rng)
            agreement = np.ones(len(candidates))
        else:
            tokens, agreement = self._generator_words(candidates)
        attrs, ok = self.language.parse_many(tokens)
        unsure = ok & (agreement < self.cfg.min_agreement)
        self.unparseable += int((~ok).sum())
        self.unsure += int(unsure.sum())
        kept = np.flatnonzero(ok & ~unsure)
        kept = kept[self._not_contradicting([candidates[i] for i in kept], attrs[kept])]
        copies = self._copies([candidates[i] for i in kept], tokens[kept])
        self._score([candidates[i] for i in kept], attrs[kept])
        return copies

    def _generator_words(self, candidates: list[Outcome]) -> tuple[np.ndarray, np.ndarray]:
        """The generator's instructions for the views that show `candidates`, and each one's agreement."""
        # One reckoning per episode for all of its chosen outcomes (they are consecutive, in step order).
        by_episode = [list(group) for _, group in itertools.groupby(candidates, key=lambda o: id(o.episode))]
        inputs = [generator_inputs(self.spec, group[0].episode, [o.step for o in group]) for group in by_episode]
        views = np.concatenate([v for v, _ in inputs])
        # Drawn words phrase a relabel as variously as the missions it stands beside (the expert draws
        # its phrasing too); greedy words say every relabel of one object the same way.
        where = np.concatenate([w for _, w in inputs])
        # Greedy words alone draw nothing: the draws stream stays where it was for the other consumers.
        drawing = self.cfg.decoding != "greedy" or self.cfg.agreement_draws > 0
        seed = int(self.rng.integers(2 ** 63)) if drawing else 0
        if self.cfg.decoding == "sample":
            return self.trainer.generate(views, where, seed=seed), np.ones(len(views))
        return self.trainer.describe(views, where, seed, rephrase=self.cfg.decoding == "rephrase",
                                     draws=self.cfg.agreement_draws)

    def train(self, budget_steps: int | None = None) -> dict[str, float]:
        """Take `budget_steps` gradient steps (the pace in learning/agent.GeneratorPace decides how many);
        evaluate on the validation pairs every `eval_every_updates` steps. Returns {} when nothing ran.

        Training waits for a first full batch of training pairs: a handful of pairs would only be
        memorised, and the CPU is better spent elsewhere until then.
        """
        steps = self.cfg.eval_every_updates if budget_steps is None else int(budget_steps)
        if steps <= 0 or self.trainer.dataset.n_train < self.cfg.batch_size:
            return {}
        loss = self.trainer.train_steps(steps)
        self._steps_since_eval += steps
        out = {"loss": loss}
        if self._steps_since_eval >= self.cfg.eval_every_updates:
            self._steps_since_eval = 0
            out.update({f"val_{k}": v for k, v in self.trainer.evaluate().items()})
        return out

    @property
    def generator_accuracy(self) -> float | None:
        return self.trainer.val_accuracy if self.trainer.evaluations else None

    @property
    def gate_open(self) -> bool:
        return self.trainer.gate_open

    def metrics(self) -> dict[str, Any]:
        out = super().metrics()
        t = self.trainer
        out.update({
            m.RELABEL_UNPARSEABLE: self.unparseable, m.RELABEL_UNSURE: self.unsure, m.RELABEL_GATED_OFF: self.gated_off,
            m.RELABEL_HELD: len(self.held), m.RELABEL_WITHHELD: self.withheld_count, m.RELABEL_GATE_OPEN: t.gate_open,
            m.RELABEL_DATASET_SIZE: len(t.dataset),
            # As of the latest evaluation (None before the first), and the dataset size it was measured at.
            m.GENERATOR_VAL_ACCURACY: self.generator_accuracy,
            m.GENERATOR_VAL_AT_PAIRS: t.val_at_pairs,
            m.GENERATOR_TRAIN_STEPS: t.steps,
            m.GENERATOR_LOSS: None if np.isnan(t.last_loss) else t.last_loss, m.GENERATOR_EVALUATIONS: t.evaluations,
        })
        return out

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state.update({"trainer": self.trainer.state_dict(), "unparseable": self.unparseable,
                      "unsure": self.unsure, "gated_off": self.gated_off, "withheld": self.withheld_count,
                      "steps_since_eval": self._steps_since_eval,
                      "held": episodes_state(list(self.held))})
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.trainer.load_state_dict(state["trainer"])
        self.unparseable, self.gated_off = int(state["unparseable"]), int(state["gated_off"])
        self.unsure, self.withheld_count = int(state.get("unsure", 0)), int(state.get("withheld", 0))
        self._steps_since_eval = int(state["steps_since_eval"])
        self.held.clear()
        self.held.extend(episodes_from_state(state["held"]) if "held" in state else [])


def relabel_batch(strategy: RelabelStrategy, episodes: list[Episode]) -> tuple[list[Episode], Withheld]:
    """What a batch of finished episodes gives the replay, as both runners store it: the originals the
    strategy keeps in, then their relabelled copies; and what it kept out (the learner still counts those
    frames). The strategy learns from the batch first (the generator's successes)."""
    strategy.observe(episodes)
    kept_out = strategy.withheld(episodes)  # read before relabelling: the gate as these episodes found it
    copies = strategy.relabel(episodes)
    out = {id(ep) for ep in kept_out}
    return [ep for ep in episodes if id(ep) not in out] + copies, Withheld.of(kept_out)


def make_relabel_strategy(cfg: Config, seed: int | RelabelerSeeds, space: ObjectSpace | None = None) -> RelabelStrategy:
    """The relabel strategy of a run config (cfg.relabel, cfg.generator, cfg.world), drawing from the
    relabeler's streams `seed` (Seeds.relabeler; an int stands for the streams of that run seed)."""
    kind = cfg.relabel.strategy
    spec = WorldSpec.of(cfg.world)
    most = cfg.relabel.max_per_episode
    if kind == "none":
        return RelabelStrategy(seed, spec, most)
    if kind == "expert":
        return ExpertRelabel(seed, spec, most)
    if kind == "noisy":
        if spec.family != "fetchattr":
            raise ValueError(f"relabel.strategy: noisy is defined on FetchAttr's attributes, not on {spec.level}")
        return NoisyExpertRelabel(space if space is not None else ObjectSpace(cfg.world), cfg.relabel.noise_p, seed,
                                  spec, most)
    if kind == "learned":
        return LearnedRelabel(cfg.generator, spec, seed, device=cfg.device, max_per_episode=most,
                              held_while_gated=cfg.relabel.held_while_gated, words=cfg.relabel.words,
                              withheld_while_gated=cfg.relabel.withheld_while_gated)
    raise ValueError(f"relabel.strategy: unknown strategy {kind!r}; choose one of {', '.join(RELABEL_STRATEGIES)}")
