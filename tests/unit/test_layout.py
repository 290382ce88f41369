"""How a host's cores are shared between the roles (launch/layout.py), and which device each part takes
(learning/devices.py). No GPU is needed: the CUDA cases check the refusal or the fallback."""
import os
import subprocess
import sys

import pytest
import torch

from higher_dist.config import ConfigError
from higher_dist.config_presets import make_config
from higher_dist.launch.layout import available_cores, default_actors, learner_alone, plan_layout
from higher_dist.learning.devices import resolve_device


@pytest.mark.parametrize("cores, actors, learner", [(1, 1, 1), (2, 1, 1), (4, 1, 2), (8, 1, 6), (16, 2, 13),
                                                    (64, 8, 55)])
def test_a_cpu_learner_takes_every_core_the_actors_and_the_relabeler_leave(cores, actors, learner):
    layout = plan_layout(cores)
    assert (layout.actors, layout.learner_threads, layout.actor_threads, layout.relabeler_threads) == (
        actors, learner, 1, 1)
    assert layout.learner_threads + layout.actors + layout.relabeler_threads <= max(cores, 3)


@pytest.mark.parametrize("cores, actors", [(2, 1), (4, 1), (16, 13), (64, 16)])
def test_a_gpu_learner_keeps_two_threads_and_the_actors_take_the_rest(cores, actors):
    layout = plan_layout(cores, learner_device="cuda")
    assert layout.actors == actors == default_actors(cores, "cuda")
    assert layout.learner_threads == min(2, cores)


def test_given_actors_and_threads_are_kept():
    layout = plan_layout(16, actors=5, learner_threads=3)
    assert (layout.actors, layout.learner_threads) == (5, 3)
    assert plan_layout(16, actors=5).learner_threads == 10
    assert plan_layout(2, actors=4).learner_threads == 1  # oversubscribed: the learner still gets one


def test_a_layout_describes_itself_in_one_line():
    text = plan_layout(16).describe()
    assert text == "16 cores: learner 13 threads on cpu, relabeler 1, 2 actors x 1 thread"


@pytest.mark.parametrize("bad", [dict(cores=0), dict(cores=4, actors=0)])
def test_impossible_layouts_are_refused(bad):
    with pytest.raises(ValueError):
        plan_layout(**bad)


def test_a_learner_alone_takes_its_host():
    assert learner_alone(8) == 6 and learner_alone(2) == 1 and learner_alone(1) == 1
    assert learner_alone(8, "cuda:0") == 2 and learner_alone(8, learner_threads=3) == 3


def test_available_cores_follows_the_cpu_affinity():
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs a machine with at least 2 cores to restrict")
    code = ("import os; from higher_dist.launch.layout import available_cores; "
            "os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); print(available_cores())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1"
    assert 1 <= available_cores() <= len(os.sched_getaffinity(0))


def test_auto_takes_cuda_only_where_torch_sees_it():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")


def test_a_cuda_device_on_a_host_without_one_is_refused_by_name():
    if torch.cuda.is_available():
        pytest.skip("this host has a CUDA device: the refusal is for hosts without one")
    with pytest.raises(ValueError, match="device: 'cuda:1'.*no CUDA device"):
        resolve_device("cuda:1")


@pytest.mark.parametrize("field, value", [("device", "gpu"), ("device", "cuda:x"), ("actor_device", "tpu"),
                                          ("torch_threads", -1)])
def test_bad_device_and_thread_settings_are_refused_by_name(field, value):
    with pytest.raises(ConfigError, match=field):
        make_config("her", "small", **{field: value})


def test_the_learner_falls_back_to_the_cpu_and_learns_there():
    from higher_dist.learning.learner import Learner
    from higher_dist.learning.random_episodes import real_episodes

    cfg = make_config("her", "small", **{"replay.min_size": 50, "dqn.batch_size": 8})
    assert cfg.device == "auto"
    core = Learner(cfg)
    if torch.cuda.is_available():
        pytest.skip("this host has a CUDA device: the CPU fallback is for hosts without one")
    assert {p.device.type for p in core.dqn.online.parameters()} == {"cpu"}
    before = [p.detach().clone() for p in core.dqn.online.parameters()]
    core.add_episodes(real_episodes(cfg.world, 20, seed=3))
    assert core.train_available(3) == 3
    assert any(not torch.equal(a, b) for a, b in zip(before, core.dqn.online.parameters()))
