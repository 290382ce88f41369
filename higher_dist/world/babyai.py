"""BabyAI's single-instruction levels (Farama Minigrid) behind the batched interface of `BatchedFetchAttr`.

A batch is B unwrapped minigrid envs stepped one after the other; what this module adds is the
batch's arrays, auto-reset, the episode bookkeeping hindsight needs (every distinct outcome the agent
achieved, and when) and the translation of missions into `babyai_language` word ids.

Views. Minigrid's image is (V, V, 3) indexed [x, y]; ours are (V, V, 4) uint8 indexed [row, col,
channel], so a BabyAI view is the image transposed plus a 4th channel that is always 0: the same
layout as FetchAttr's views. Channels: minigrid's object index (0..10), colour index (0..5) and
state (0..2). The agent is at row V-1, column V//2, facing up; while it carries an object, minigrid
draws that object in the agent's own cell.

Episodes. Outside strict mode reaching, opening or picking the wrong object does not end a BabyAI
episode: the agent goes on. An episode ends when the level's own verifier accepts its mission
(terminated, outcome SUCCESS, reward 1 - 0.9 * steps / max_steps) or at the level's step limit
(truncated, outcome TIMEOUT). A step that does both counts as a success only.

Achieved outcomes. What counts is what the level counts: at each reset the env gets one of minigrid's
own verifiers (the level's kind: `PickupInstr`, `GoToInstr` or `OpenInstr`) per distinct (colour, type)
of the objects its instructions may name, reset as the level resets its own, and stepped as the level
steps its own (object positions refreshed after a drop). The first step a verifier accepts is an outcome,
recorded as (colour, type, location mask, plural): plural when several objects match (the level would say
"a"); the mask has bit i set when LOCS[i] ("on your left", ...) describes the achieved object from the
agent's start, by minigrid's own location rule, so a description that names a location can be judged.
A go-to is recorded only while the object is in front: minigrid also accepts facing the cell where an
object lay before the agent picked it up, which no view shows. `picked` / `pick_step` report the first
outcome, `later_achieved` / `later_step` up to MAX_LATER more.

Seeds. Env i is reset the first time with the seed `default_rng([seed, i]).integers(2**63 - 1)`
(or `default_rng(env_seeds[i])...`) and afterwards without one, continuing its own generator: env i
of a batch replays a single `gym.make(level_id)` env reset once with that seed. 63 bits, not 31: the
many evaluation episodes of many runs must not meet on one reset seed by a birthday collision.
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from higher_dist.world import babyai_language as lang
from higher_dist.world.grid import StepResult, check_actions
from minigrid.envs.babyai.core.verifier import GoToInstr, ObjDesc, OpenInstr, PickupInstr

from higher_dist.world.babyai_levels import (LevelFacts, _quiet, is_pickup_level, level_facts,  # noqa: F401
                                             pickup_levels, supported_levels)
from higher_dist.world.spec import (BABYAI_ACTION_NAMES, BABYAI_CHANNEL_VALUES, MAX_LATER, MAX_OUTCOMES, RUNNING,
                                    SUCCESS, TIMEOUT)

N_BABYAI_ACTIONS = len(BABYAI_ACTION_NAMES)
ACTION_PICKUP = BABYAI_ACTION_NAMES.index("pickup")
ACTION_DROP = BABYAI_ACTION_NAMES.index("drop")
_VERIFIERS = {"pickup": PickupInstr, "goto": GoToInstr, "open": OpenInstr}
CHANNEL_VALUES = BABYAI_CHANNEL_VALUES  # distinct values per view channel: object, colour, state, unused
_COLOR_INDEX = {c: i for i, c in enumerate(lang.COLORS)}
_TYPE_INDEX = {t: i for i, t in enumerate(lang.TYPES)}


class OutcomeWatch:
    """One episode's achieved outcomes on one env, judged by the level's own verifier class."""

    def __init__(self, env, kind: str, language: lang.BabyAILanguage):
        self.kind, self.found = kind, []  # found: (step, (colour, type, location mask, plural)) in order
        # Which location words describe each object, from the agent's start: minigrid's own location rule
        # (ObjDesc.find_matching_objs at reset), bit i for LOCS[i]; objects outside the start room have none.
        self.loc_masks: dict[int, int] = {}
        for bit, loc in enumerate(lang.LOCS):
            for obj in ObjDesc(None, None, loc).find_matching_objs(env)[0]:
                self.loc_masks[id(obj)] = self.loc_masks.get(id(obj), 0) | (1 << bit)
        names = {lang.TYPES[t] for t in language.types}
        descriptions = dict.fromkeys((cell.color, cell.type) for cell in env.grid.grid
                                     if cell is not None and cell.type in names)
        self.pending = []
        for color, type_ in descriptions:
            verifier = _VERIFIERS[kind](ObjDesc(type_, color))
            verifier.reset_verifier(env)
            attrs = (_COLOR_INDEX[color], _TYPE_INDEX[type_], int(len(verifier.desc.obj_set) > 1))
            self.pending.append((verifier, attrs))

    def step(self, env, action: int, step: int) -> bool:
        """Judge the step just taken (index `step` of the episode); True when it achieved something new."""
        # As the level does for its own verifier after a drop: objects may have moved. Only a go-to's
        # verifier reads positions; pickup and open verifiers compare the objects themselves.
        if action == ACTION_DROP and self.kind == "goto":
            for verifier, _ in self.pending:
                verifier.update_objs_poss()
        new, still = False, []
        for verifier, attrs in self.pending:
            obj = verifier.verify(action) == "success" and self._achieved_object(env, attrs)
            if obj:
                if len(self.found) < MAX_OUTCOMES:
                    color, type_, plural = attrs
                    self.found.append((step, (color, type_, self.loc_masks.get(id(obj), 0), plural)))
                    new = True
            else:
                still.append((verifier, attrs))
        self.pending = still
        return new

    def _achieved_object(self, env, attrs):
        """The object a step the verifier accepted achieved: the one now carried, or the one in front (the
        door just opened, the object reached). None for a go-to without it in front (see the module's
        docstring)."""
        obj = env.carrying if self.kind == "pickup" else env.grid.get(*env.front_pos)
        if obj is None or (_COLOR_INDEX.get(obj.color), _TYPE_INDEX.get(obj.type)) != attrs[:2]:
            return None
        return obj


class BatchedBabyAI:
    """B envs of one supported BabyAI level stepped together; finished ones are reset in place by `step`.

    Arrays handed out (views, missions, goals, picks) are never written to afterwards: state arrays
    are replaced, not edited, so callers may keep them without copying.
    """

    def __init__(self, level_id: str, batch_size: int, seed: int = 0, env_seeds=None,
                 max_steps: int | None = None):
        """`max_steps`: the episode step limit, None for the level's own; it also scales the
        success reward, 1 - 0.9 * steps / max_steps, as in minigrid."""
        for name, value in (("batch_size", batch_size), ("max_steps", 1 if max_steps is None else max_steps)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name}: must be an integer >= 1, got {value!r}")
        self.facts = level_facts(level_id)
        self.language = lang.LANGUAGES[self.facts.kind]
        self.level_id, self.batch_size = level_id, int(batch_size)
        self.view_size = self.facts.view_size
        self.max_steps = self.facts.max_steps if max_steps is None else int(max_steps)
        # Every supported level takes `max_steps` and then keeps it fixed instead of deriving it per episode.
        kwargs = {} if max_steps is None else {"max_steps": self.max_steps}
        self._envs = [gym.make(level_id, **kwargs).unwrapped for _ in range(self.batch_size)]
        self._init_seeds(seed, env_seeds)
        b, v = self.batch_size, self.view_size
        self._images: list[np.ndarray] = [np.zeros((v, v, 3), np.uint8)] * b  # minigrid's, [x, y]
        self._steps = np.zeros(b, dtype=np.int32)
        self._mission = np.zeros((b, lang.MISSION_LEN), dtype=np.int64)
        self._goal = np.full((b, 4), -1, dtype=np.int8)
        self._picked = np.full((b, 4), -1, dtype=np.int8)
        self._pick_step = np.full(b, -1, dtype=np.int32)
        self._later = np.full((b, MAX_LATER, 4), -1, dtype=np.int8)
        self._later_step = np.full((b, MAX_LATER), -1, dtype=np.int32)
        self._watches: list[OutcomeWatch | None] = [None] * b
        self._missions_seen: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._started = False

    # ----------------------------------------------------------------------------------- seeding

    def _init_seeds(self, seed, env_seeds) -> None:
        if env_seeds is None:
            env_seeds = [[int(seed), i] for i in range(self.batch_size)]
        elif len(env_seeds) != self.batch_size:
            raise ValueError(f"env_seeds: needs one seed per env ({self.batch_size}), got {len(env_seeds)}")
        # The seed of each env's first reset; None once used, so later resets continue its generator.
        self._first_seeds = [int(np.random.default_rng(s).integers(2**63 - 1)) for s in env_seeds]

    # ------------------------------------------------------------------------------ observations

    def _to_views(self, images) -> np.ndarray:
        v = self.view_size
        out = np.zeros((len(images), v, v, 4), dtype=np.uint8)
        out[..., :3] = np.stack(images).transpose(0, 2, 1, 3)
        return out

    def view(self) -> np.ndarray:
        """The current observation of every env, (B, V, V, 4) uint8."""
        return self._to_views(self._images)

    @property
    def mission(self) -> np.ndarray:
        return self._mission

    @property
    def goal(self) -> np.ndarray:
        return self._goal

    @property
    def steps(self) -> np.ndarray:
        return self._steps.copy()

    @property
    def agent_dir(self) -> np.ndarray:
        """(B,) minigrid directions: 0 right (+x), 1 down (+y), 2 left, 3 up."""
        return np.array([env.agent_dir for env in self._envs], dtype=np.int64)

    @property
    def envs(self) -> list:
        """The unwrapped minigrid envs (for tests, rendering and debugging; do not step them)."""
        return self._envs

    def render_rgb(self, env_index: int, tile_size: int = 16) -> np.ndarray:
        """Minigrid's own full-level RGB frame of env `env_index`, (H, W, 3) uint8."""
        return self._envs[env_index].get_frame(highlight=True, tile_size=tile_size)

    # ---------------------------------------------------------------------------------- resetting

    def reset(self, seed: int | None = None):
        """Start a new episode in every env; `seed` re-seeds all envs by the (seed, i) scheme.
        Returns (view (B, V, V, 4) uint8, mission (B, L) int64)."""
        if seed is not None:
            self._init_seeds(seed, None)
        self._reset_envs(range(self.batch_size))
        self._started = True
        return self.view(), self._mission

    def _encode_mission(self, text: str) -> tuple[np.ndarray, np.ndarray]:
        known = self._missions_seen.get(text)
        if known is None:
            try:
                tokens = lang.encode(text)
            except ValueError as error:
                raise ValueError(f"level {self.level_id}: mission {text!r} does not encode: {error}") from None
            goal = self.language.parse(tokens)
            if goal is None:
                raise ValueError(f"level {self.level_id}: mission {text!r} is not a {self.facts.kind} sentence")
            known = self._missions_seen[text] = (tokens, goal)
        return known

    def _reset_envs(self, envs) -> None:
        """New episodes for `envs` (indices); replaces the per-episode state arrays."""
        self._mission, self._goal = self._mission.copy(), self._goal.copy()
        self._copy_outcomes()
        with _quiet():
            for i in envs:
                env, seed = self._envs[i], self._first_seeds[i]
                self._first_seeds[i] = None
                obs, _ = env.reset(seed=seed)
                self._images[i] = obs["image"]
                self._mission[i], self._goal[i] = self._encode_mission(env.mission)
                self._watches[i] = OutcomeWatch(env, self.facts.kind, self.language)
        envs = list(envs)
        self._steps[envs] = 0
        self._picked[envs] = -1
        self._pick_step[envs] = -1
        self._later[envs] = -1
        self._later_step[envs] = -1

    def _copy_outcomes(self) -> None:
        """Fresh outcome arrays before editing them: the ones handed out stay as they were."""
        self._picked, self._pick_step = self._picked.copy(), self._pick_step.copy()
        self._later, self._later_step = self._later.copy(), self._later_step.copy()

    def _record(self, i: int) -> None:
        """Write env i's outcomes into the (already copied) outcome arrays."""
        found = self._watches[i].found
        self._pick_step[i], self._picked[i] = found[0]
        for k, (step, attrs) in enumerate(found[1:]):
            self._later_step[i, k], self._later[i, k] = step, attrs

    # ------------------------------------------------------------------------------------ stepping

    def _check_actions(self, actions) -> np.ndarray:
        return check_actions(actions, self.batch_size, BABYAI_ACTION_NAMES)

    def step(self, actions) -> StepResult:
        """Apply one action per env; finished envs start a new episode in place (see StepResult)."""
        if not self._started:
            raise RuntimeError("BatchedBabyAI.step: call reset() first")
        acts = self._check_actions(actions).tolist()
        images, envs, steps = self._images, self._envs, self._steps
        rewards, ended, dirs, achieved = [], [], [], []
        for i, env in enumerate(envs):
            obs, reward, terminated, truncated, _ = env.step(acts[i])
            images[i] = obs["image"]
            rewards.append(reward)
            dirs.append(env.agent_dir)
            if terminated or truncated:
                ended.append((i, bool(terminated)))
            if self._watches[i].step(env, acts[i], int(steps[i])):
                achieved.append(i)
        steps += 1
        b = self.batch_size
        reward = np.array(rewards, dtype=np.float32)
        terminated, truncated = np.zeros(b, dtype=bool), np.zeros(b, dtype=bool)
        outcome = np.full(b, RUNNING, dtype=np.int8)
        for i, success in ended:
            (terminated if success else truncated)[i] = True
            outcome[i] = SUCCESS if success else TIMEOUT
        if achieved:
            self._copy_outcomes()
            for i in achieved:
                self._record(i)
        final_view = self._to_views(images)
        length, goal, mission_done = steps.copy(), self._goal, self._mission
        picked, pick_step, later, later_step = self._picked, self._pick_step, self._later, self._later_step
        view = final_view
        if ended:
            finished = [i for i, _ in ended]
            self._reset_envs(finished)
            view = final_view.copy()
            view[finished] = self._to_views([images[i] for i in finished])
        return StepResult(view=view, mission=self._mission, reward=reward, terminated=terminated,
                          truncated=truncated, final_view=final_view, outcome=outcome, length=length,
                          picked=picked, goal=goal, mission_done=mission_done,
                          final_dir=np.array(dirs, dtype=np.int64), pick_step=pick_step,
                          later_achieved=later, later_step=later_step)
