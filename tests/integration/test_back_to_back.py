"""Runs that follow one another on the same ports: the second starts while the first's connections sit in
TIME_WAIT, and the port check must not mistake that for a running cluster. A port something still listens
on must go on being refused."""
from __future__ import annotations

import socket
import time

import psutil
import pytest

from hd_harness import Proc, RunWatch, config_flags, entry
from higher_dist.launch.topology import Endpoints, check_free, free_base_port

pytestmark = pytest.mark.slow


def _time_wait_ports(ports: set[int]) -> set[int]:
    return {c.laddr.port for c in psutil.net_connections(kind="tcp")
            if c.status == psutil.CONN_TIME_WAIT and c.laddr and c.laddr.port in ports}


def _run(tmp_path, name: str, port: int) -> Proc:
    run_dir = tmp_path / name
    argv = entry("cluster", *config_flags(1500, actors=1), "--port-base", str(port), "--no-dashboard",
                 "--run-dir", str(run_dir))
    proc = Proc(argv, tmp_path / f"{name}.out", tmp_path)
    watch = RunWatch(run_dir, [proc])
    try:
        assert proc.wait(240) == 0, watch.diagnostics()
    finally:
        watch.cleanup()
    assert "learner finished the run" in watch.log("cluster"), watch.diagnostics()
    return proc


def _leave_in_time_wait(port: int) -> None:
    """A connection on `port` whose server side closes first: the kernel keeps (127.0.0.1, port) in
    TIME_WAIT for about a minute, as after a run whose learner closed its sockets before its peers."""
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", port))
    listener.listen()
    client = socket.create_connection(("127.0.0.1", port))
    served, _ = listener.accept()
    served.close()  # the server side closes first: its end goes to TIME_WAIT
    time.sleep(0.1)
    client.close()
    listener.close()


def test_two_clusters_one_right_after_the_other_on_the_same_ports(tmp_path):
    port = free_base_port()
    _run(tmp_path, "first", port)
    ports = set(range(port, port + 5))
    # Whatever the first run left, make sure the case is there: the control port in TIME_WAIT.
    _leave_in_time_wait(port)
    assert port in _time_wait_ports(ports), "the control port is not in TIME_WAIT: the case is not exercised"
    _run(tmp_path, "second", port)


def test_a_port_something_listens_on_is_still_refused():
    port = free_base_port()
    holder = socket.socket()
    holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # binds even over an earlier run's TIME_WAIT
    holder.bind(("127.0.0.1", port + 2))
    holder.listen()
    try:
        with pytest.raises(ValueError, match=f"weights port {port + 2}"):
            check_free(Endpoints.from_base("127.0.0.1", port))
    finally:
        holder.close()
