"""higher-reproduce's default --parallel: one run per core this process may use, counted as the run layout
counts them (CPU affinity, then the cgroup quota), not the machine's core count."""
from __future__ import annotations

import os

import pytest

from higher_dist.launch import layout
from higher_dist.reproduce import plan as plan_mod
from higher_dist.reproduce.cli import parser


@pytest.mark.parametrize("affinity, quota, expected", [({0, 1, 2, 3, 4}, None, 5), ({0, 1, 2, 3, 4}, 3, 3),
                                                       ({7}, None, 1)])
def test_default_parallel_follows_the_cores_this_process_may_use(monkeypatch, affinity, quota, expected):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: affinity)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)  # the machine's count is not what a process may use
    monkeypatch.setattr(layout, "_cgroup_quota", lambda: quota)
    assert plan_mod.default_parallel() == expected
    help_text = " ".join(parser().format_help().split())  # argparse wraps lines
    assert (f"default: one per core this process may use, its CPU affinity and cgroup quota: {expected})"
            in help_text)
