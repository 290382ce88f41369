"""A run's random streams (learning/seeds.py): one SeedSequence per run, a child per (role, index, purpose).

No two streams of any run coincide, two run seeds never evaluate on the same episode, one run seed
always draws the same streams, and the builder's components really draw from the streams named for them.
"""
from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
import torch

from higher_dist.config import EvalConfig
from higher_dist.config_presets import make_config
from higher_dist.learning.agent import AgentBuilder
from higher_dist.learning.hindsight.generator import InstructionGenerator
from higher_dist.learning.networks import QNetwork
from higher_dist.learning.seeds import Purpose, RelabelerSeeds, Role, Seeds
from higher_dist.world.grid import BatchedFetchAttr

RUN_SEEDS = range(10)
ACTORS = 64
ENVS_PER_ACTOR = 16


def named_streams(seeds: Seeds) -> dict[str, int]:
    """Every seed a run hands out by name (per-env seeds included), keyed by what it is for."""
    out = {"learner_torch": seeds.learner_torch, "learner_init": seeds.learner_init,
           "learner_replay": seeds.learner_replay}
    out.update({f"relabeler_{k}": v for k, v in vars(seeds.relabeler).items()})
    for a in range(ACTORS):
        out[f"actor{a}_torch"] = seeds.actor_torch(a)
        out[f"actor{a}_exploration"] = seeds.actor_exploration(a)
        out.update({f"actor{a}_env{i}": s for i, s in enumerate(seeds.actor_env_seeds(a, ENVS_PER_ACTOR))})
    return out


def test_no_two_streams_coincide_over_run_seeds_roles_actors_and_purposes():
    seen: dict[int, tuple] = {}
    for run, role, index, purpose in itertools.product(RUN_SEEDS, Role, range(ACTORS), Purpose):
        value = Seeds(run).integer(role, index, purpose)
        assert 0 <= value < 2**63  # a torch seed, an int64, a msgpack int
        assert value not in seen, f"{(run, role.name, index, purpose.name)} repeats {seen.get(value)}"
        seen[value] = (run, role.name, index, purpose.name)
    named: dict[int, str] = {}
    for run in RUN_SEEDS:
        for name, value in named_streams(Seeds(run)).items():
            assert value not in named, f"seed {run} {name} repeats {named.get(value)}"
            named[value] = f"seed {run} {name}"
    # The first draws of the generators made from them differ too (not only the integers).
    firsts = [np.random.default_rng(v).integers(2**63) for v in list(named)[:5000]]
    assert len(set(firsts)) == len(firsts)


def test_the_old_coincidences_are_gone():
    """At seed 0 the learner, actor 0's torch and exploration seeds were all 0, and the relabeler's
    seed was actor 1's torch seed."""
    s = Seeds(0)
    assert len({s.learner_torch, s.learner_init, s.actor_torch(0), s.actor_exploration(0)}) == 4
    assert s.relabeler.draws != s.actor_torch(1) and s.relabeler.generator_init != s.actor_torch(1)
    # Run 0 at frame 1 and run 1 at frame 0 both evaluated on seed 10001.
    assert not set(Seeds(0).evaluation_env_seeds(1, 256)) & set(Seeds(1).evaluation_env_seeds(0, 256))


def test_two_run_seeds_never_share_an_evaluation_episode():
    episodes = EvalConfig().episodes
    per_run = {run: [s for frames in range(0, 2_000_001, 10_000)
                     for s in Seeds(run).evaluation_env_seeds(frames, episodes)] for run in RUN_SEEDS}
    everything = [s for seeds in per_run.values() for s in seeds]
    assert len(everything) == len(RUN_SEEDS) * 201 * episodes
    assert len(set(everything)) == len(everything)  # across runs, across frame counts, across episodes
    # Reproducible per (run seed, frame count); a longer evaluation extends a shorter one.
    assert Seeds(4).evaluation_env_seeds(30_000, episodes) == Seeds(4).evaluation_env_seeds(30_000, episodes)
    assert Seeds(4).evaluation_env_seeds(30_000, 8) == Seeds(4).evaluation_env_seeds(30_000, 16)[:8]


def recording_policy(seen: list):
    """A greedy policy that always picks (episodes end at once) and keeps the first views it is shown."""
    def q_fn(obs, mission):
        if not seen:
            seen.append(obs[:, -1].copy())
        q = np.zeros((len(obs), 4), np.float32)
        q[:, 3] = 1.0
        return q
    return q_fn


def test_evaluation_plays_the_episodes_of_its_seeds():
    cfg = make_config("her", "small", seed=6)
    cfg = replace(cfg, eval=replace(cfg.eval, episodes=12))
    seen: list = []
    AgentBuilder(cfg).evaluate(recording_policy(seen), frames=40_000)
    expected, _ = BatchedFetchAttr(cfg.world, 12, env_seeds=Seeds(6).evaluation_env_seeds(40_000, 12)).reset()
    assert np.array_equal(seen[0], expected)
    other: list = []
    AgentBuilder(replace(cfg, seed=7)).evaluate(recording_policy(other), frames=40_000)
    assert not np.array_equal(other[0], expected)


def test_two_runs_with_one_seed_draw_the_same_streams_and_other_seeds_do_not():
    torch.set_num_threads(1)
    a, b, c = (AgentBuilder(make_config("higher", "small", seed=s)) for s in (3, 3, 4))
    assert a.seeds == b.seeds and named_streams(a.seeds) == named_streams(b.seeds)
    assert not set(named_streams(a.seeds).values()) & set(named_streams(c.seeds).values())
    for actor in (0, 5):
        assert np.array_equal(a.collector(actor).observation()[0], b.collector(actor).observation()[0])
        assert not np.array_equal(a.collector(actor).observation()[0], c.collector(actor).observation()[0])
        assert a.exploration_rng(actor).random() == b.exploration_rng(actor).random()
        assert a.exploration_rng(actor).random() != c.exploration_rng(actor).random()
    assert a.relabel_strategy().rng.random() == b.relabel_strategy().rng.random() != c.relabel_strategy().rng.random()
    wa, wb, wc = (x.learner().dqn.weights_numpy() for x in (a, b, c))
    assert all(np.array_equal(wa[k], wb[k]) for k in wa)
    assert not all(np.array_equal(wa[k], wc[k]) for k in wa)


def initial_weights(cfg, spec, seed: int) -> dict[str, torch.Tensor]:
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return QNetwork(cfg.network, spec).state_dict()


def test_the_builders_components_draw_from_their_own_streams():
    torch.set_num_threads(1)
    cfg = make_config("higher", "small", seed=2)
    agent, seeds = AgentBuilder(cfg), Seeds(2)
    core = agent.learner()
    online = core.dqn.online.state_dict()

    def same(weights):
        return all(torch.equal(online[k], weights[k]) for k in online)

    # The learner's network starts from its own stream, not from an actor's torch seed.
    assert same(initial_weights(cfg, agent.spec, seeds.learner_init))
    for actor in range(4):
        assert not same(initial_weights(cfg, agent.spec, seeds.actor_torch(actor)))
    assert not same(initial_weights(cfg, agent.spec, seeds.learner_torch))
    assert core.replay._rng.bit_generator.state == np.random.default_rng(seeds.learner_replay).bit_generator.state
    # The relabeler: its draws, its generator's initialisation, dataset split and minibatches.
    strategy = agent.relabel_strategy()
    rs = seeds.relabeler
    assert strategy.rng.bit_generator.state == np.random.default_rng(rs.draws).bit_generator.state
    assert strategy.trainer.rng.bit_generator.state == np.random.default_rng(rs.generator_batches).bit_generator.state
    assert strategy.trainer.dataset.seed == rs.dataset_split
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(rs.generator_init)
        generator = InstructionGenerator(cfg.generator, agent.spec).state_dict()
    assert all(torch.equal(v, generator[k]) for k, v in strategy.trainer.model.state_dict().items())
    actor_seeds = {v for a in range(ACTORS) for v in
                   (seeds.actor_torch(a), seeds.actor_exploration(a), *seeds.actor_env_seeds(a, ENVS_PER_ACTOR))}
    assert not set(vars(rs).values()) & actor_seeds
    # Each actor: its envs from its env seeds, its exploration from its exploration seed.
    for actor in (0, 3):
        n = cfg.envs_per_actor
        world, _ = BatchedFetchAttr(cfg.world, n, env_seeds=seeds.actor_env_seeds(actor, n)).reset()
        assert np.array_equal(agent.collector(actor).observation()[0][:, -1], world)
        assert agent.exploration_rng(actor).bit_generator.state == \
            np.random.default_rng(seeds.actor_exploration(actor)).bit_generator.state


def test_an_int_seed_given_to_a_relabel_strategy_stands_for_that_runs_streams():
    streams = Seeds(5).relabeler
    assert RelabelerSeeds.of(5) == streams and RelabelerSeeds.of(streams) is streams
    assert RelabelerSeeds.of(6) != streams


@pytest.mark.parametrize("bad", [-1, 1.5, "3", True])
def test_a_bad_run_seed_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="seed: must be a non-negative integer"):
        Seeds(bad)
