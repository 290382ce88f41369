"""The roles' allocator settings and the opt-in tracemalloc trace (launch/memory.py)."""
from __future__ import annotations

import subprocess
import sys

from higher_dist.launch.memory import ALLOCATOR_ENV, MemoryTrace, role_env


def test_roles_get_the_bounded_arenas_unless_the_user_chose():
    assert role_env({"PATH": "/bin"})["MALLOC_ARENA_MAX"] == ALLOCATOR_ENV["MALLOC_ARENA_MAX"]
    assert role_env({"MALLOC_ARENA_MAX": "8"})["MALLOC_ARENA_MAX"] == "8"  # a user's own setting is kept
    assert role_env({"PATH": "/bin"})["PATH"] == "/bin"


def test_arenas_are_bounded_by_mallopt_unless_the_user_set_them():
    code = "from higher_dist.launch.memory import bound_arenas; print(bound_arenas())"
    run = lambda env: subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,  # noqa: E731
                                     text=True, timeout=60).stdout.strip()
    assert run({"PATH": "/usr/bin:/bin"}) == "True"  # glibc: this machine's libc
    assert run({"PATH": "/usr/bin:/bin", "MALLOC_ARENA_MAX": "4"}) == "False"


def test_the_trace_names_the_line_that_grows(tmp_path):
    import tracemalloc

    trace = MemoryTrace(tmp_path / "t.txt", every_s=1.0, warmup_s=0.0)
    hoard = []
    try:
        trace.begin()
        for _ in range(2000):
            hoard.append(bytearray(1024))  # ~2 MiB that stays live: this line must top the list
        trace.write_once()
    finally:
        tracemalloc.stop()
    text = (tmp_path / "t.txt").read_text().splitlines()
    assert text[0].startswith("tracing from")
    assert "rss=" in text[1] and "traced=" in text[1]
    top = text[2]
    assert "test_memory_trace.py:" in top and float(top.split()[0]) >= 2000, text[:4]  # KiB
    assert len(hoard) == 2000


def test_a_cli_process_traces_only_when_asked(tmp_path):
    code = ("import sys, time; from higher_dist.launch.memory import trace_from_env; "
            "t = trace_from_env('probe'); print(t is not None); time.sleep(1.5)")
    env = {"HIGHER_MEMTRACE_DIR": str(tmp_path / "mt"), "HIGHER_MEMTRACE_EVERY_S": "0.5",
           "HIGHER_MEMTRACE_WARMUP_S": "0.2", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "True", out.stderr
    files = list((tmp_path / "mt").glob("probe-*.txt"))
    assert len(files) == 1
    lines = files[0].read_text().splitlines()
    assert lines[0].startswith("tracing from") and any(line.startswith("t=") for line in lines[1:]), lines
    quiet = subprocess.run([sys.executable, "-c", code], env={"PATH": "/usr/bin:/bin"}, capture_output=True,
                           text=True, timeout=60)
    assert quiet.stdout.strip() == "False", quiet.stderr
