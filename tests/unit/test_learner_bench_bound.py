"""The learner's compute bound (bench/compute_bound.py): FLOPs counted on real modules against exact
formulas, the Q-network's count against its layer shapes, and `higher-bench learner --set`. Speed is
printed, never asserted."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from higher_dist.bench import compute_bound, main
from higher_dist.bench.learner_bench import bench_config, synthetic_batch
from higher_dist.config import ConfigError, DQNConfig, NetworkConfig
from higher_dist.learning.dqn import DQNUpdater

torch.set_num_threads(1)

SMALL = NetworkConfig(embed_dim=4, conv_channels=(8, 8), frame_stack=2, word_embed_dim=8, text_hidden=8, hidden=16)


def test_linear_counts_two_flops_per_multiply_add_and_its_backward_twice_that():
    b, n_in, n_out = 5, 7, 3
    layer, x = nn.Linear(n_in, n_out), torch.randn(b, n_in, requires_grad=True)
    assert compute_bound.record(lambda: layer(x)).total == 2 * b * n_in * n_out
    # Backward: the input's gradient and the weight's, one product each.
    assert compute_bound.record(lambda: layer(x).sum().backward()).total == 3 * 2 * b * n_in * n_out


def test_conv2d_counts_every_output_cell_of_every_kernel():
    b, c_in, c_out, k, side, pad = 3, 4, 6, 3, 7, 0
    conv, x = nn.Conv2d(c_in, c_out, k, padding=pad), torch.randn(b, c_in, side, side)
    out_side = side - k + 1 + 2 * pad
    assert compute_bound.record(lambda: conv(x)).total == 2 * b * c_in * c_out * k * k * out_side ** 2


@pytest.mark.parametrize("film_blocks, text", [(0, "gru"), (2, "gru"), (0, "bow")])
def test_q_network_forwards_match_the_count_from_layer_shapes(film_blocks, text):
    cfg = NetworkConfig(**{**SMALL.__dict__, "film_blocks": film_blocks, "text": text})
    learner = DQNUpdater(cfg, DQNConfig(compile=False))
    t = learner._tensors(synthetic_batch(np.random.default_rng(0), 16, cfg.frame_stack))
    steps = int((t["mission"] != 0).sum(dim=1).max())
    net, b = learner.online, 16
    analytic = compute_bound.analytic_forward_flops(net, steps)
    with torch.no_grad():
        text = net.encode_mission(t["mission"])
        assert compute_bound.record(lambda: net.encode_mission(t["mission"])).total == b * analytic["text"]
        assert compute_bound.record(lambda: net.q_values(t["obs"], text)).total == b * analytic["q"]
    # The whole update: the backward skips a few products (no gradient for the GRU's initial state).
    counted = compute_bound.count_update(learner, t).total / b
    expected = compute_bound.analytic_update_flops(net, steps)
    assert 0.98 * expected <= counted <= expected
    assert all(p.grad is None for p in net.parameters())  # counting leaves no gradient behind


def test_bound_figures_and_their_lines():
    learner = DQNUpdater(SMALL, DQNConfig(compile=False))
    t = learner._tensors(synthetic_batch(np.random.default_rng(1), 8, SMALL.frame_stack))
    figures = compute_bound.bound(learner, t)
    assert figures["flops_per_sample"] == compute_bound.count_update(learner, t).total / 8
    assert figures["bound_samples_per_s"] > 0 and figures["gflops"] > 0
    lines = compute_bound.bound_lines(figures, 8, {"defaults": figures["bound_samples_per_s"] / 2})
    assert "MFLOP/sample counted" in lines[0] and lines[1].endswith("= 50% of the bound")
    assert lines[-1].startswith("machine: ") and "cores" in lines[-1]


def test_learner_bench_takes_network_options_and_prints_the_bound(capsys):
    argv = ["learner", "--only", "--batch-sizes", "8", "--seconds", "0.05", "--set", "network.film_blocks=1"]
    assert main(argv) == 0
    out = capsys.readouterr().out.strip().splitlines()
    last = json.loads(out[-1])
    assert last["network"]["film_blocks"] == 1
    assert last["bound"]["batch_size"] == 8 and last["bound"]["flops_per_sample"] > 0
    assert last["bound_ratio"] == last["bound"]["ratio"] > 0  # read by `higher-bench all`'s summary
    assert any(line.startswith("compute bound at B=8") for line in out)


def test_learner_bench_refuses_a_bad_network_option_naming_it():
    with pytest.raises(ConfigError, match="network.film_blocks"):
        bench_config(["network.film_blocks=-1"])


def test_learner_bench_measures_the_recurrent_core_in_samples_the_ratio_counts(capsys):
    argv = ["learner", "--only", "--batch-sizes", "8", "--seconds", "0.2", "--set", 'network.core="gru"',
            "--set", "network.frame_stack=1", "--set", "dqn.sequence_batch=2"]
    assert main(argv) == 0
    out = capsys.readouterr().out.strip().splitlines()
    last = json.loads(out[-1])
    assert last["network"]["core"] == "gru" and "bound" not in last
    cell = last["rows"]["eager (all levers off)"]["b8"]
    # Two whole episodes of 5-40 steps per update: between 10 and 80 samples each, not the batch size.
    assert 10 <= cell["samples_per_s"] / cell["updates_per_s"] <= 80
    assert any("frame-stack network only" in line for line in out)


def test_learner_bench_sends_the_recurrent_core_from_the_raw_step_to_the_replay_path(capsys):
    assert main(["learner", "--net", "core=gru", "--net", "frame_stack=1", "--batch-sizes", "8"]) == 2
    assert "--set network.core=gru" in capsys.readouterr().err
