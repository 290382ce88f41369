"""End to end, under faults: roles killed with SIGKILL mid-run (the learner too: the running roles rejoin
it) and garbage on every socket a peer can reach. Real processes, real sockets, 127.0.0.1 only.

The cluster tests share one running cluster (module-scoped), in file order: garbage first (so its reject
counts start from zero), then an actor and the relabeler are killed, then the cluster is stopped.
"""
from __future__ import annotations

import signal

import msgpack
import numpy as np
import psutil
import pytest
import zmq

from hd_harness import MAX_STEPS, VIEW_SIZE, Proc, RunWatch, learner_pid, role_row, start_cluster
from higher_dist.launch.topology import Endpoints
from higher_dist.learning.episode import SUCCESS, WRONG_PICK, Episode
from higher_dist.rundir import RunDir
from higher_dist.wire import codec
from higher_dist.wire.episodes import pack_episodes
from higher_dist.wire.schema import PROTOCOL_VERSION
from higher_dist.world.language import MISSION_LEN

pytestmark = pytest.mark.slow


# ----------------------------------------------------------------------------------------------- the cluster

class Cluster:
    def __init__(self, watch: RunWatch, launcher: Proc, port_base: int):
        self.watch, self.launcher = watch, launcher
        self.endpoints = Endpoints.from_base("127.0.0.1", port_base)
        self.run_dir = watch.run_dir

    def records(self):
        return self.watch.records()

    def restarts_logged(self) -> list[str]:
        return [line for line in self.watch.log("cluster").splitlines()
                if "exited with" in line or "restarting" in line or "giving up" in line]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    base = tmp_path_factory.mktemp("faults")
    watch, launcher, port_base = start_cluster(base / "run", base, frames=10_000_000)
    try:
        c = Cluster(watch, launcher, port_base)
        # Running, learning and relabelling before any fault.
        watch.wait_for("updates > 50 and both actors and the relabeler alive",
                       lambda r: r["updates"] > 50 and all(
                           (row := role_row(r, role, i)) is not None and row["state"] == "alive"
                           for role, i in (("actor", 0), ("actor", 1), ("relabeler", 0))), timeout=150)
        yield c
    finally:
        watch.cleanup()


def _alive_pid(record, role: str, index: int) -> int:
    row = role_row(record, role, index)
    assert row is not None and row["state"] == "alive", record["roles"]
    proc = psutil.Process(row["pid"])
    assert f"{role}_main" in " ".join(proc.cmdline())
    return row["pid"]


# --------------------------------------------------------------------------------------------------- garbage

def _episode(length: int = 3, outcome: int = WRONG_PICK) -> Episode:
    rng = np.random.default_rng(length)
    frames = np.zeros((length + 1, VIEW_SIZE, VIEW_SIZE, 4), np.uint8)
    frames[..., 0] = rng.integers(0, 3, size=frames.shape[:-1])  # unseen / empty / wall cells
    rewards = np.zeros(length, np.float32)
    rewards[-1] = 1.0 if outcome == SUCCESS else 0.0
    mission = np.zeros(MISSION_LEN, np.int64)
    mission[:3] = (1, 3, 2)
    return Episode(frames=frames, actions=np.full(length, 3, np.uint8), rewards=rewards, mission=mission,
                   outcome=outcome, picked=np.array([0, 0, 0, 0], np.int8), goal=np.array([1, 1, 0, 0], np.int8))


def _episodes_message(episodes=None, tamper=None, version=None) -> list[bytes]:
    """An `episodes` message built the way the roles build it, then tampered with (the sender's encode does
    not scan array values, so out-of-range values go out as they would from a buggy or hostile peer)."""
    fields, arrays = pack_episodes(episodes or [_episode(), _episode(4, SUCCESS)])
    arrays = {k: np.array(v) for k, v in arrays.items()}
    if tamper is not None:
        tamper(arrays)
    frames = [bytes(f) for f in codec.encode("episodes", fields, arrays, sender="garbage")]
    if version is not None:
        header = msgpack.unpackb(frames[0], raw=False)
        header["v"] = version
        frames[0] = msgpack.packb(header, use_bin_type=True)
    return frames


def _set(name, index, value):
    def tamper(arrays):
        arrays[name][index] = value
    return tamper


def _control_garbage(rng) -> list[list[bytes]]:
    hello = codec.encode("hello", {"role": "actor", "host": "x", "pid": 1, "protocol": PROTOCOL_VERSION})
    header = msgpack.unpackb(hello[0], raw=False)
    header["v"] = 99
    heartbeat = codec.encode("heartbeat", {"role": "actor", "id": 5, "state": "running", "counters": {}})
    stop = codec.encode("stop", {"reason": "a stranger says stop"})
    return [
        [rng.bytes(200)],  # random bytes
        [b""],  # an empty body
        [msgpack.packb([1, 2, 3])],  # msgpack, but not a header
        [msgpack.packb(header, use_bin_type=True)],  # a hello of another protocol version: refused, answered
        [bytes(heartbeat[0]), b"extra frame"],  # a truncated / extended multipart message
        # Valid, but from a peer that never said hello, and not a type the learner takes from anyone.
        # (A stranger's heartbeat or stats would be adopted as a role: that is how roles rejoin a
        # restarted learner.)
        [bytes(stop[0])],
    ]


def _experience_garbage(rng) -> list[list[bytes]]:
    truncated = _episodes_message()[:-1]  # the last array frame is missing
    return [
        [rng.bytes(1000)],
        truncated,
        _episodes_message(version=PROTOCOL_VERSION + 1),  # a peer of another version
        _episodes_message(tamper=_set("actions", 0, 9)),  # out-of-range action
        _episodes_message(tamper=_set("rewards", 1, np.nan)),
        _episodes_message(tamper=_set("frames", (0, 0, 0, 0), 200)),  # view channel out of range
        _episodes_message(episodes=[_episode(MAX_STEPS + 5)]),  # longer than this run's max_steps
        [codec.encode_weights(3, {"w": np.zeros(2, np.float32)})],  # valid message, wrong socket
    ]


def _relabeler_garbage(rng) -> list[list[bytes]]:
    def small_view(arrays):
        arrays["frames"] = np.ascontiguousarray(arrays["frames"][:, :5, :5, :])
    return [
        [rng.bytes(300)],
        _episodes_message(tamper=_set("actions", 2, 77)),
        _episodes_message(tamper=small_view),  # a 5x5 view in a 7x7 run
        _episodes_message(tamper=_set("lengths", 0, 2)),  # lengths disagree with the arrays
    ]


def _send_all(sock: zmq.Socket, messages: list[list[bytes]]) -> None:
    for frames in messages:
        sock.send_multipart(frames)  # blocks at most SNDTIMEO when the reader holds back


def test_garbage_is_counted_and_dropped_and_learning_goes_on(cluster):
    before = cluster.records()[-1]
    assert before["learner_rejected"] == 0 and before["rejected_messages"] == 0
    pids = {(role, i): _alive_pid(before, role, i) for role, i in (("learner", 0), ("actor", 0), ("actor", 1), ("relabeler", 0))}
    learner = learner_pid(cluster.launcher)
    assert learner is not None

    rng = np.random.default_rng(1234)
    control_msgs, experience_msgs, relabeler_msgs = (_control_garbage(rng), _experience_garbage(rng),
                                                     _relabeler_garbage(rng))
    ctx = zmq.Context()
    try:
        def sock(kind, endpoint):
            s = ctx.socket(kind)
            s.setsockopt(zmq.LINGER, 5000)
            s.setsockopt(zmq.SNDTIMEO, 30_000)
            s.setsockopt(zmq.RCVTIMEO, 15_000)
            s.connect(endpoint)
            return s

        control = sock(zmq.DEALER, cluster.endpoints.control)
        experience = sock(zmq.PUSH, cluster.endpoints.experience)
        relabeler = sock(zmq.PUSH, cluster.endpoints.episodes)
        _send_all(control, control_msgs)
        # The hello of another version is answered with a refusal that says why.
        reply = codec.decode(control.recv_multipart())
        assert reply.type == "refuse" and "protocol version mismatch" in reply.fields["reason"], reply
        _send_all(experience, experience_msgs)
        _send_all(relabeler, relabeler_msgs)
        for s in (control, experience, relabeler):
            s.close()  # linger: what is queued is delivered first
        ctx.term()
    finally:
        if not ctx.closed:
            ctx.destroy(linger=0)

    n_learner = len(control_msgs) + len(experience_msgs)
    seen = cluster.watch.wait_for(
        f"the learner's {n_learner} and the relabeler's {len(relabeler_msgs)} rejects counted",
        lambda r: r["learner_rejected"] >= n_learner
        and (role_row(r, "relabeler", 0) or {}).get("rejected", 0) >= len(relabeler_msgs), timeout=90)
    # Every bad message is counted once, and nothing else was.
    assert seen["learner_rejected"] == n_learner
    assert role_row(seen, "relabeler", 0)["rejected"] == len(relabeler_msgs)
    assert seen["rejected_messages"] == n_learner + len(relabeler_msgs)
    assert "dropped invalid message" in cluster.watch.log("learner")
    assert "dropped invalid message" in cluster.watch.log("relabeler")

    # Learning goes on, with the same processes: nothing crashed, nothing was restarted.
    after = cluster.watch.wait_for("updates growing after the garbage",
                                   lambda r: r["updates"] > seen["updates"] + 20, timeout=90)
    assert {(row["role"], row["id"]) for row in after["roles"]} == set(pids), after["roles"]  # no stranger
    for (role, i), pid in pids.items():
        row = role_row(after, role, i)
        assert row["pid"] == pid and row["state"] == "alive", after["roles"]
    assert learner_pid(cluster.launcher) == learner
    assert cluster.launcher.running()
    assert cluster.restarts_logged() == []
    assert after["frames"] > seen["frames"]  # the actors' experience still flows


# ------------------------------------------------------------------------------------------------- SIGKILLs

def test_killed_actor_is_restarted_and_learning_goes_on(cluster):
    before = cluster.records()[-1]
    old_pid = _alive_pid(before, "actor", 1)
    n = len(cluster.records())
    cluster.watch.tracker.add(old_pid)
    psutil.Process(old_pid).send_signal(signal.SIGKILL)
    killed_at = cluster.records()[-1]["updates"]

    cluster.watch.wait_until("the supervisor notices the dead actor and restarts it",
                             lambda: "actor1 exited with code -9" in cluster.watch.log("cluster")
                             and "restarting actor1" in cluster.watch.log("cluster"), timeout=30)
    assert not psutil.pid_exists(old_pid) or psutil.Process(old_pid).status() == psutil.STATUS_ZOMBIE

    def restarted(r):
        row = role_row(r, "actor", 1)
        return row is not None and row["pid"] != old_pid and row["state"] == "alive" and row["restarts"] >= 1
    back = cluster.watch.wait_for("actor 1 back under a new pid", restarted, timeout=90, after=n)
    new_pid = role_row(back, "actor", 1)["pid"]
    assert "actor_main" in " ".join(psutil.Process(new_pid).cmdline())
    assert role_row(back, "actor", 0)["pid"] == role_row(before, "actor", 0)["pid"]  # the other one untouched

    # The learner kept learning across the kill, and goes on with the new actor's weights version moving.
    later = cluster.watch.wait_for("updates still growing after the restart",
                                   lambda r: r["updates"] > max(back["updates"], killed_at) + 20
                                   and role_row(r, "actor", 1)["weights_lag"] is not None, timeout=90)
    assert later["updates"] > killed_at
    log = cluster.watch.log("cluster")
    assert "learner exited" not in log and "relabeler exited" not in log


def _checkpointed_dataset_size(run_dir) -> int:
    state = RunDir(run_dir).load_checkpoint("relabeler")
    return 0 if state is None else len(state["trainer"]["dataset"]["views"])


def test_killed_relabeler_resumes_its_generator_and_dataset(cluster):
    # A periodic relabeler checkpoint holding a real dataset must exist before the kill.
    size = cluster.watch.wait_until("a relabeler checkpoint with >= 20 generator pairs",
                                    lambda: (n := _checkpointed_dataset_size(cluster.run_dir)) >= 20 and n,
                                    timeout=90)
    before = cluster.records()[-1]
    old_pid = _alive_pid(before, "relabeler", 0)
    n = len(cluster.records())
    log_offset = len(cluster.watch.log("relabeler"))
    cluster.watch.tracker.add(old_pid)
    psutil.Process(old_pid).send_signal(signal.SIGKILL)
    killed_at = before["updates"]

    cluster.watch.wait_until("the supervisor restarts the relabeler",
                             lambda: "relabeler exited with code -9" in cluster.watch.log("cluster")
                             and "restarting relabeler" in cluster.watch.log("cluster"), timeout=30)
    cluster.watch.wait_until("the restarted relabeler says it resumed",
                             lambda: "resumed the relabeler's generator and dataset"
                             in cluster.watch.log("relabeler")[log_offset:], timeout=90)

    def restarted(r):
        row = role_row(r, "relabeler", 0)
        return (row is not None and row["pid"] != old_pid and row["state"] == "alive"
                and r.get("relabel_dataset_size") is not None)
    back = cluster.watch.wait_for("the relabeler back, reporting its dataset", restarted, timeout=90, after=n)
    # The dataset only grows (capacity 2000): resumed, it holds at least what the checkpoint had.
    assert back["relabel_dataset_size"] >= size, (back["relabel_dataset_size"], size)
    assert back["relabel_dataset_size"] > 0

    later = cluster.watch.wait_for("updates growing after the relabeler's restart",
                                   lambda r: r["updates"] > max(back["updates"], killed_at) + 20, timeout=90)
    assert later["relabel_dataset_size"] >= size
    assert "learner exited" not in cluster.watch.log("cluster")


def test_killed_learner_resumes_and_the_running_roles_rejoin_it(cluster):
    ckpt = cluster.watch.wait_until("a learner checkpoint with updates",
                                    lambda: (s := RunDir(cluster.run_dir).load_checkpoint("learner"))
                                    and s["core"]["counters"]["updates"] > 0 and s, timeout=60)
    before = cluster.records()[-1]
    others = {(role, i): _alive_pid(before, role, i) for role, i in (("actor", 0), ("actor", 1), ("relabeler", 0))}
    old_pid = learner_pid(cluster.launcher)
    cluster.watch.tracker.add(old_pid)
    log_offset = len(cluster.watch.log("cluster"))
    psutil.Process(old_pid).send_signal(signal.SIGKILL)

    cluster.watch.wait_until("the supervisor restarts the learner with --resume",
                             lambda: "restarting learner" in cluster.watch.log("cluster")[log_offset:], timeout=30)
    n = len(cluster.records())
    first = cluster.watch.wait_for("a record from the resumed learner", lambda r: True, timeout=60, after=n)

    def rejoined(r):
        # With its replay restored the learner may update before any new frame arrives: wait for both.
        return (r["updates"] > ckpt["core"]["counters"]["updates"] + 20 and r["frames"] > first["frames"]
                and all((row := role_row(r, role, i)) is not None and row["state"] == "alive" and row["pid"] == pid
                        for (role, i), pid in others.items()))
    after = cluster.watch.wait_for("the same actors and relabeler rejoin, learning goes on", rejoined,
                                   timeout=120, after=n)
    # Counters continued from the checkpoint rather than from zero.
    assert first["updates"] >= ckpt["core"]["counters"]["updates"]
    assert first["frames"] >= ckpt["core"]["counters"]["frames"]
    # The replay came back with it (in the checkpoint by default): never below what the checkpoint held.
    assert "replay" in ckpt["core"] and ckpt["core"]["replay"]["size"] > 0
    assert first["replay_size"] >= ckpt["core"]["replay"]["size"]
    assert after["frames"] > first["frames"]  # experience flows again through the untouched roles
    assert learner_pid(cluster.launcher) not in (None, old_pid)


def test_cluster_stops_cleanly_after_the_faults(cluster):
    cluster.launcher.snapshot()
    cluster.watch.records()
    cluster.launcher.send(signal.SIGTERM)
    rc = cluster.launcher.wait(40)
    assert rc == 0, cluster.watch.diagnostics()
    # Restarted roles included: every process of the run is gone.
    assert cluster.watch.leftovers() == []
    assert len(cluster.watch.tracker.seen) >= 7  # launcher, learner x2, relabeler x2, actor x3
