"""A single-environment Gymnasium view of the batched world (a batch of one, not a second world).

`FetchAttrEnv` subclasses `gymnasium.Env` when gymnasium is installed and is a plain class
otherwise: gymnasium is an optional dependency of the package. The batched world resets finished
envs inside `step`; this wrapper hides that: the terminal step returns the *final* observation, and
the episode the batched world already started is handed out by the next `reset()` (so a sequence of
episodes here equals env 0 of a `BatchedFetchAttr` with the same seed).

Observation: {"image": (V, V, 4) uint8 view, "direction": 0 up .. 3 left, "mission": text}.
"""
from __future__ import annotations

import numpy as np

from higher_dist.config import WorldConfig
from higher_dist.config_presets import world_by_name
from higher_dist.world import language
from higher_dist.world.grid import N_ACTIONS, BatchedFetchAttr

try:
    import gymnasium
    from gymnasium import spaces
    _EnvBase = gymnasium.Env
except ModuleNotFoundError as error:  # only a missing gymnasium is tolerated, not a broken import
    if error.name != "gymnasium":
        raise
    gymnasium, spaces, _EnvBase = None, None, object

ENV_IDS = {"HIGhER/FetchAttr-v0": "paper", "HIGhER/FetchAttr-Small-v0": "small"}
_MISSION_CHARS = frozenset("".join(language.VOCAB[3:]) + " ")
_MISSION_MAX_CHARS = language.MISSION_LEN * (max(len(w) for w in language.VOCAB) + 1)


class FetchAttrEnv(_EnvBase):
    """FetchAttr as a Gymnasium environment. `world_cfg`: a WorldConfig, a world name ("paper",
    "small") or None for the paper world. Actions: 0 left, 1 right, 2 forward, 3 pick."""

    metadata = {"render_modes": []}

    def __init__(self, world_cfg: WorldConfig | str | None = None, goal_set: str = "train"):
        if world_cfg is None or isinstance(world_cfg, str):
            world_cfg = world_by_name(world_cfg or "paper")
        self.world_cfg = world_cfg
        self.world = BatchedFetchAttr(world_cfg, 1, seed=0, goal_set=goal_set)
        v = world_cfg.view_size
        if spaces is not None:
            self.action_space = spaces.Discrete(N_ACTIONS)
            self.observation_space = spaces.Dict({
                "image": spaces.Box(0, 255, shape=(v, v, 4), dtype=np.uint8),
                "direction": spaces.Discrete(4),
                "mission": spaces.Text(max_length=_MISSION_MAX_CHARS, charset=_MISSION_CHARS),
            })
        self._next_episode = None  # (view, mission) of the episode started by the batched auto-reset
        self._needs_reset = True

    def _observation(self, view: np.ndarray, mission: np.ndarray, direction: int) -> dict:
        return {"image": view.copy(), "direction": int(direction), "mission": language.decode(mission)}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if _EnvBase is not object:
            super().reset(seed=seed)  # keeps Gymnasium's own np_random consistent with the seed
        if seed is None and self._next_episode is not None:
            view, mission = self._next_episode  # the new episode the batched world already drew
        else:
            views, missions = self.world.reset(seed=seed)
            view, mission = views[0], missions[0]
        self._next_episode = None
        self._needs_reset = False
        return self._observation(view, mission, self.world.agent_dir[0]), {}

    def step(self, action):
        if self._needs_reset:
            raise RuntimeError("FetchAttrEnv.step: call reset() before stepping (again)")
        action = np.asarray(action)
        if action.shape not in ((), (1,)):
            raise ValueError(f"action: expected one integer in 0..{N_ACTIONS - 1}, got shape {action.shape}")
        result = self.world.step(action.reshape(1))  # the world checks dtype and range
        terminated, truncated = bool(result.terminated[0]), bool(result.truncated[0])
        info = {"outcome": int(result.outcome[0]), "length": int(result.length[0])}
        if terminated or truncated:
            # The batched world has already reset this env: report the episode that just ended and keep
            # the new one for reset().
            self._next_episode = (result.view[0], result.mission[0])
            self._needs_reset = True
            info.update(picked=result.picked[0].copy(), goal=result.goal[0].copy())
        observation = self._observation(result.final_view[0], result.mission_done[0], result.final_dir[0])
        return observation, float(result.reward[0]), terminated, truncated, info


def register_gym_envs() -> None:
    """Register the Gymnasium ids (idempotent). Raises ImportError when gymnasium is not installed."""
    if gymnasium is None:
        raise ImportError("register_gym_envs needs gymnasium (pip install 'higher-dist[minigrid]')")
    for env_id, world_name in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point="higher_dist.world.gym_env:FetchAttrEnv",
                               kwargs={"world_cfg": world_name})
