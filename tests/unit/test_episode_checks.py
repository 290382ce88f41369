"""Every episode that passes `unpack_episodes` is one the run can store and learn from; every class of
well-formed but wrong episode is dropped under its own reason (issue 12's boundary checks)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from higher_dist.config_presets import make_config
from higher_dist.learning.learner import Learner
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.wire import WireError, decode, encode, pack_episodes, unpack_episodes
from support.mutate import MUTATIONS, Pools, hostile_message
from higher_dist.world.spec import WorldSpec

CFG = {name: make_config("her", name, **{"replay.min_size": 50}) for name in ("paper", "small")}
SPECS = {name: WorldSpec.of(cfg.world) for name, cfg in CFG.items()}
POOLS = {name: Pools.of(real_episodes(cfg.world, 300, seed=5)) for name, cfg in CFG.items()}


def _unpack(frames, spec, **kw):
    rejects: list[str] = []
    episodes = unpack_episodes(decode(frames), spec, reject=rejects.append, **kw)
    return episodes, rejects


@pytest.mark.parametrize("world", ["paper", "small"])
def test_honest_episodes_pass(world):
    episodes = real_episodes(CFG[world].world, 90, seed=1, relabelled=True)
    back, rejects = _unpack(encode("episodes", *pack_episodes(episodes)), SPECS[world])
    assert rejects == [] and len(back) == len(episodes)


@pytest.mark.parametrize("world", ["paper", "small"])
@pytest.mark.parametrize("kind", sorted(MUTATIONS))
@pytest.mark.parametrize("to_relabeler", [False, True])
def test_each_mutation_is_dropped_under_its_reason(world, kind, to_relabeler):
    rng = np.random.default_rng(abs(hash((world, kind))) % 1000)
    spec = SPECS[world]
    for _ in range(3):
        h = hostile_message(kind, POOLS[world], rng, spec, "actor0" if to_relabeler else "relabeler", to_relabeler)
        try:
            back, rejects = _unpack(h.frames, spec, allow_relabelled=not to_relabeler,
                                    n_actors=CFG[world].actors)
        except WireError as e:
            assert (h.rejects, h.reason) == (1, e.reason), (kind, e)
            continue
        assert back == [] and rejects == [h.reason] * h.rejects, (kind, rejects[:3])


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["frames", "actions", "rewards", "mission", "outcome", "picked", "goal", "relabelled",
                        "lengths", "actor_id"]), st.integers(0, 2 ** 31), st.integers(0, 255))
def test_whatever_passes_can_be_stored(array_name, position, value):
    """Any one value changed anywhere (within the schema's ranges): what passes the boundary never makes
    the learner's replay or counters raise."""
    episodes = real_episodes(CFG["small"].world, 6, seed=position % 7, relabelled=True)
    fields, arrays = pack_episodes(episodes)
    flat = arrays[array_name].reshape(-1)
    flat[position % flat.size] = value if array_name != "picked" and array_name != "goal" else value % 8 - 1
    try:
        msg = decode(encode("episodes", fields, arrays))
    except WireError:
        return  # the schema refused it: not this test's concern
    try:
        back, _ = _unpack([bytes(f) for f in encode("episodes", fields, arrays)], SPECS["small"],
                          n_actors=2)
    except WireError:
        return
    core = Learner(CFG["small"])
    core.add_episodes(back)  # must not raise
    assert core.episodes + core.relabelled_episodes == len(back)
    assert msg.type == "episodes"
