"""Dead reckoning (world/reckoning.py) against minigrid's own location rule: on random episodes of single-room
levels of each family, the location mask reckoned from the frames and actions alone equals the mask the world
recorded for each achieved outcome (minigrid's ObjDesc.find_matching_objs at reset), for every outcome whose
object had not been moved by a drop before it."""
from __future__ import annotations

import numpy as np
import pytest

from higher_dist.world.babyai import BABYAI_ACTION_NAMES, BatchedBabyAI
from higher_dist.world.reckoning import start_relative_masks
from higher_dist.world.spec import WorldSpec
from higher_dist.config_presets import make_config

PICKUP, DROP, TOGGLE = (BABYAI_ACTION_NAMES.index(a) for a in ("pickup", "drop", "toggle"))
MOVES = np.array([0.25, 0.25, 0.5])  # left, right, forward


def biased_actions(world: BatchedBabyAI, rng) -> np.ndarray:
    """Mostly moves; toggle a closed door or pick up an object in front (so outcomes happen); drop sometimes."""
    out = []
    for env in world.envs:
        front = env.grid.get(*env.front_pos)
        if front is not None and front.type == "door" and not front.is_open and rng.random() < 0.7:
            out.append(TOGGLE)
        elif front is not None and front.can_pickup() and env.carrying is None and rng.random() < 0.5:
            out.append(PICKUP)
        elif env.carrying is not None and front is None and rng.random() < 0.2:
            out.append(DROP)
        else:
            out.append(int(rng.choice(3, p=MOVES)))
    return np.array(out)


def episodes(level: str, n: int, seed: int):
    """n finished episodes: (frames (T+1, V, V, 4), actions (T,), [(step, recorded location mask), ...])."""
    batch = 16
    world = BatchedBabyAI(level, batch, env_seeds=[[seed, i] for i in range(batch)], max_steps=40)
    view, _ = world.reset()
    frames = [[view[i]] for i in range(batch)]
    actions: list[list[int]] = [[] for _ in range(batch)]
    rng = np.random.default_rng(seed)
    done = []
    while len(done) < n:
        acts = biased_actions(world, rng)
        result = world.step(acts)
        for i in range(batch):
            actions[i].append(int(acts[i]))
            frames[i].append(result.final_view[i])
            if result.done[i]:
                recorded = []
                if result.pick_step[i] >= 0:
                    recorded.append((int(result.pick_step[i]), int(result.picked[i, 2])))
                    recorded += [(int(s), int(a[2])) for s, a in zip(result.later_step[i], result.later_achieved[i])
                                 if s >= 0]
                done.append((np.stack(frames[i]), np.array(actions[i]), recorded))
                frames[i], actions[i] = [result.view[i]], []
    return done[:n]


@pytest.mark.parametrize("level", ["BabyAI-OpenDoorLoc-v0", "BabyAI-OpenDoor-v0", "BabyAI-PickupLoc-v0",
                                   "BabyAI-GoToLocal-v0"])
def test_reckoned_location_is_minigrids(level):
    spec = WorldSpec.of(make_config("her", level).world)
    checked = two_bits = 0
    for frames, actions, recorded in episodes(level, 250, seed=len(level)):
        for step, mask in recorded:
            if (actions[:step + 1] == DROP).any():  # the object may lie elsewhere than at the start
                continue
            got = start_relative_masks(frames, actions, [step + spec.outcome_view_offset])[0]
            assert got == mask, (level, step, actions[:step + 1].tolist(), got, mask)
            checked += 1
            two_bits += bin(mask).count("1") == 2
    assert checked >= 60 and two_bits >= 20, (checked, two_bits)


def test_turns_and_blocked_moves():
    """A hand-made episode: a wall ahead blocks the first forward, the agent turns right and walks two cells,
    then turns left: the cell it faces is ahead and to the right of the start."""
    v = 7
    frames = np.zeros((6, v, v, 4), np.uint8)
    frames[:, :, :, 0] = 1  # empty everywhere
    frames[0, v - 2, v // 2, 0] = 2  # a wall in front at the start
    actions = np.array([2, 1, 2, 2, 0])  # forward (blocked), right, forward, forward, left
    masks = start_relative_masks(frames, actions, [0, 2, 4, 5])
    # frame 0: the cell ahead; frame 2: facing right from the start cell; frame 4: two cells right, facing
    # right; frame 5: two right, facing ahead again -> the cell ahead-right.
    assert masks.tolist() == [4, 2, 2, 2 | 4]
    with pytest.raises(ValueError):
        start_relative_masks(frames, actions, [6])
