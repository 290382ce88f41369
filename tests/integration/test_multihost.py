"""Across hosts, for real: three Linux network namespaces on a bridge, CURVE on.

    head  learner + relabeler (each a CURVE server with its own authenticator)
    node  one actor
    evil  an outsider that knows the control endpoint and the servers' public key

A small-world run trains with frames flowing across the bridge; from `evil`, a client with no keys and one
with a key pair that is not on the allow-list can neither say hello, push episodes (to the learner or the
relabeler), receive weights nor read telemetry, while a listed key (the positive control) can; the actor's
link is cut for 10 s mid-run and the run goes on: no process dies, frames flow again, the run finishes.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from higher_dist.wire.security import generate_keys

from hd_harness import Proc, RunWatch, config_flags, entry, role_row
from netns import Hosts, netns_unavailable

FRAMES = 6000  # a few thousand frames on the small world (CI time matters)
ATTACK_S = 5.0  # how long each outsider tries: it must receive nothing in that time
CUT_S = 10.0
PORT = 5555  # each host is a namespace of its own: the default ports are free there
ATTACKER = Path(__file__).with_name("multihost_attacker.py")

_reason = netns_unavailable()
pytestmark = pytest.mark.skipif(_reason is not None, reason=_reason or "")


def attacks(hosts: Hosts, control: str, server_key: str, push: bool, **keys: str) -> dict[str, dict]:
    """Run one outsider per keys folder ("none": no keys) at once from `evil`; their reports by name."""
    procs = {name: subprocess.Popen(hosts.exec_argv("evil", [sys.executable, str(ATTACKER), control, folder,
                                                             str(ATTACK_S), server_key,
                                                             "push" if push else "nopush"]),
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name, folder in keys.items()}
    reports = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        reports[name] = json.loads(out.strip().splitlines()[-1])
    return reports


@pytest.fixture
def cluster(tmp_path):
    hosts = Hosts(["head", "node", "evil"])
    keys, intruder = tmp_path / "keys", tmp_path / "intruder"
    generate_keys(keys)
    generate_keys(intruder)  # a valid pair the servers do not list
    head = hosts.addr("head")
    control = f"tcp://{head}:{PORT}"
    run_dir = tmp_path / "run"
    flags = config_flags(FRAMES, actors=1)
    learner = Proc(hosts.exec_argv("head", entry("learner", *flags, "--run-dir", run_dir, "--host", head,
                                                 "--port-base", PORT, "--keys", keys)), tmp_path / "learner.out", tmp_path)
    watch = RunWatch(run_dir, [learner])
    try:
        relabeler = watch.add(Proc(hosts.exec_argv("head", entry("relabeler", "--learner", control, "--keys", keys,
                                                                 "--state-dir", run_dir)),
                                   tmp_path / "relabeler.out", tmp_path))
        actor = watch.add(Proc(hosts.exec_argv("node", entry("actor", "--learner", control, "--keys", keys)),
                               tmp_path / "actor.out", tmp_path))
        yield hosts, watch, (learner, relabeler, actor), control, keys, intruder
    finally:
        watch.cleanup()
        hosts.destroy()


def test_secure_run_across_namespaces(cluster):
    hosts, watch, (learner, relabeler, actor), control, keys, intruder = cluster
    timeline: list[str] = []
    t0 = time.monotonic()

    def note(text: str) -> None:
        timeline.append(f"{time.monotonic() - t0:6.1f} s  {text}")
        print(timeline[-1], flush=True)

    first = watch.wait_for("frames flowing with keys across hosts", lambda r: r["frames"] > 0, timeout=180)
    note(f"frames flowing: {first['frames']} frames, {first['updates']} updates")

    # Cut the actor's host off, and meanwhile attack from the third host (the head stays reachable).
    at_cut = watch.last()
    hosts.link("node", up=False)
    cut_at = time.monotonic()
    note(f"link of `node` down at {at_cut['frames']} frames")
    server_key = str(Path(keys) / "server.key")
    results = attacks(hosts, control, server_key, True, **{"no keys": "none", "unlisted key": str(intruder)})
    note("attacks done: " + json.dumps(results))
    time.sleep(max(CUT_S - (time.monotonic() - cut_at), 0.0))
    during = watch.last()
    hosts.link("node", up=True)
    note(f"link of `node` up again after {time.monotonic() - cut_at:.1f} s, at {during['frames']} frames")
    # The positive control: the same outsider with a listed key gets through on every channel.
    listed = attacks(hosts, control, server_key, False, listed=str(keys))["listed"]
    note("listed client: " + json.dumps(listed))

    for who, report in results.items():
        for channel, got in report.items():
            assert got["handshakes_ok"] == 0 and got["sent"] == 0 and got["received"] == 0, (who, channel, got)
        assert sum(got["handshakes_failed"] for got in report.values()) > 0, (who, report)  # it did try
    assert all(listed[c]["handshakes_ok"] > 0 for c in listed), listed
    assert listed["control"]["received"] > 0 and listed["weights"]["received"] > 0 \
        and listed["telemetry"]["received"] > 0, listed

    # More than the experience path's buffers could have held when the link went down (about 550 frames).
    after = watch.wait_for("frames flowing again after the link returned",
                           lambda r: r["frames"] >= during["frames"] + 1000 and (role_row(r, "actor", 0) or {}).get(
                               "state") == "alive", timeout=120)
    note(f"frames flowing again: {after['frames']} frames; roles "
         + ", ".join(f"{row['role']} {row['id']} {row['state']}" for row in after["roles"]))
    assert all(p.running() or p.returncode == 0 for p in (learner, relabeler, actor)), watch.diagnostics()
    assert [row["id"] for row in after["roles"] if row["role"] == "actor"] == [0]  # one actor, one number
    # The cut and the reconnect are shorter than role_grace_s: the actor is never listed dead meanwhile.
    states = {(role_row(r, "actor", 0) or {}).get("state") for r in watch.records() if r["time"] >= at_cut["time"]}
    assert "dead" not in states, states

    assert learner.wait(240) == 0, "the learner did not finish the run\n" + watch.diagnostics()
    note("learner finished the run")
    assert relabeler.wait(30) == 0 and actor.wait(30) == 0, watch.diagnostics()
    final = watch.records()[-1]
    note(f"final: {final['frames']} frames, {final['updates']} updates, rejected {final['rejected_messages']}")
    assert final["frames"] >= FRAMES and final["updates"] > 0
    (Path(watch.run_dir) / "timeline.txt").write_text("\n".join(timeline) + "\n")
