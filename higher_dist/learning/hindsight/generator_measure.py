"""The generator's measurement: how well it learns from N expert pairs (the `generator` experiment of
`higher-reproduce` and `higher-bench generator`).

Pairs are drawn as the relabeler would see them from successful episodes of the paper world: the
view just before a pick, with the goal in the cell in front of the agent, other objects and walls
around, and the expert's instruction for the goal. Each layout is laid out by hand in a
`BatchedFetchAttr` (`set_state`): the agent stands on a random free cell facing a random direction
whose front cell is inside the room, the goal lies in that cell and the world's other objects lie on
random free cells, drawn from the same goal set as the goal (as the world's own resets draw them).
So the view is the world's own rendering, not a hand-made array.

The generator trains on all N pairs, then is measured on fresh pairs of two kinds:
- seen:   goals among the 240 training goals (new layouts and wordings),
- unseen: goals among the 60 held-out goals, never described in training (compositional transfer).
Accuracy is semantic: the parsed object must match all four attributes (exact match).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch

from higher_dist.config import GeneratorConfig, WorldConfig
from higher_dist.learning.hindsight.generator import GeneratorTrainer
from higher_dist.world.grid import BatchedFetchAttr
from higher_dist.world.language import expert_tokens
from higher_dist.world.spec import WorldSpec

_DIRECTIONS = np.array([(-1, 0), (0, 1), (1, 0), (0, -1)])  # (drow, dcol) of up, right, down, left
_LAYOUT_BATCH = 256


def make_pairs(world: WorldConfig, n: int, goal_set: str, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n (view, instruction) pairs as seen before a pick of the goal: (views (n,V,V,4) uint8,
    missions (n,L) int64, goals (n,4) int8). Goals and the other objects come from `goal_set`."""
    batch = min(n, _LAYOUT_BATCH)
    env = BatchedFetchAttr(world, batch, seed=int(rng.integers(2**31)), goal_set=goal_set)
    pool = env.space.objects(goal_set)
    room, n_obj = world.room_size, world.n_objects
    views = np.zeros((n, world.view_size, world.view_size, 4), np.uint8)
    goals = pool[rng.integers(len(pool), size=n)]
    missions = expert_tokens(goals, rng)
    for start in range(0, n, batch):
        count = min(batch, n - start)
        for i in range(count):
            # Agent on a free cell, facing a direction whose front cell is also a free cell.
            while True:
                agent = rng.integers(1, room + 1, size=2)
                direction = int(rng.integers(4))
                front = agent + _DIRECTIONS[direction]
                if 1 <= front[0] <= room and 1 <= front[1] <= room:
                    break
            free = [(r, c) for r in range(1, room + 1) for c in range(1, room + 1)
                    if (r, c) != tuple(agent) and (r, c) != tuple(front)]
            spots = rng.choice(len(free), size=min(n_obj - 1, len(free)), replace=False)
            others = pool[rng.integers(len(pool), size=len(spots))]
            objects = [(tuple(front), goals[start + i])] + [(free[s], o) for s, o in zip(spots, others)]
            env.set_state(i, tuple(agent), direction, objects, goals[start + i], missions[start + i])
        views[start:start + count] = env.view()[:count]
    return views, missions, goals


def measure_generator(pairs: int, steps: int, seed: int, world: WorldConfig, eval_pairs: int,
        cfg: GeneratorConfig | None = None, log=print) -> dict:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    train = make_pairs(world, pairs, "train", rng)
    seen = make_pairs(world, eval_pairs, "train", rng)
    unseen = make_pairs(world, eval_pairs, "heldout", rng)
    data_s = time.perf_counter() - t0
    # All N pairs train (the dataset's own validation split is made negligible): the held-out
    # measures below use fresh pairs instead.
    cfg = replace(cfg or GeneratorConfig(), capacity=max(pairs, 10), val_fraction=1e-9)
    trainer = GeneratorTrainer(cfg, WorldSpec.of(world), seed=seed)
    trainer.dataset.add_many(train[0], train[1])
    t1 = time.perf_counter()
    chunk = max(1, min(500, steps))
    done = 0
    while done < steps:
        n = min(chunk, steps - done)
        loss = trainer.train_steps(n)
        done += n
        log(f"  step {done:6d}  loss {loss:.3f}  ({time.perf_counter() - t1:.1f} s)")
    train_s = time.perf_counter() - t1
    results = {name: trainer.evaluate_pairs(views, missions)
               for name, (views, missions, _) in (("seen", seen), ("unseen", unseen))}
    return {"pairs": pairs, "steps": steps, "seed": seed, "world": world.name, "eval_pairs": eval_pairs,
            "seen": results["seen"], "unseen": results["unseen"],
            "seen_exact_match": round(results["seen"]["exact"], 4),
            "unseen_exact_match": round(results["unseen"]["exact"], 4),
            "train_s": round(train_s, 1), "steps_per_s": round(steps / max(train_s, 1e-9), 1),
            "data_s": round(data_s, 1)}
