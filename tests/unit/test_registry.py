"""The learner's table of roles (liveness, lag) and its rate meter: pure bookkeeping, no sockets."""
import time

import pytest

from higher_dist.roles.registry import NoSlot, RateMeter, RoleRegistry


def test_silent_roles_are_marked_dead_and_stopping_ones_stopped():
    reg = RoleRegistry(dead_after_s=10.0)
    a = reg.hello("actor", 0, b"a0", "host", 11)
    reg.hello("actor", 1, b"a1", "host", 12)
    r = reg.hello("relabeler", 0, b"r0", "host", 13)
    a.stats["weights_version"] = 80
    a.last_seen -= 30  # silent for 30 s
    r.stopped = True
    rows = {(row["role"], row["id"]): row for row in reg.table(learner_version=100)}
    assert rows[("actor", 0)]["state"] == "dead" and rows[("actor", 0)]["weights_lag"] == 20
    assert rows[("actor", 1)]["state"] == "alive" and rows[("actor", 1)]["weights_lag"] is None
    assert rows[("relabeler", 0)]["state"] == "stopped"
    assert reg.seen(b"a0") is a and reg.seen(b"nobody") is None


def test_a_restarted_role_replaces_its_old_entry():
    reg = RoleRegistry()
    reg.hello("actor", 0, b"old", "h", 1)
    new = reg.hello("actor", 0, b"new", "h", 2)
    assert reg.roles[("actor", 0)] is new and new.pid == 2
    assert len(reg.table(0)) == 1


def test_rate_meter_measures_over_windows_and_keeps_the_rate_on_a_short_one():
    meter = RateMeter(min_window_s=0.5)
    assert meter(0, now=0.0) == 0.0
    assert meter(100, now=1.0) == 100.0
    assert meter(101, now=1.1) == 100.0  # 0.1 s is too short a window to mean anything
    assert meter(150, now=2.0) == 50.0  # measured from the last full window (t=1, 100)


def test_numbers_are_kept_per_connection_reused_after_death_and_capped():
    reg = RoleRegistry(dead_after_s=10.0)
    first = reg.assign("actor", b"a", -1, capacity=2, now=100.0)
    reg.hello("actor", first, b"a", "h", 1)
    # The same connection saying hello again (e.g. while the relabeler is not yet registered) keeps it.
    assert reg.assign("actor", b"a", -1, capacity=2, now=101.0) == first == 0
    second = reg.assign("actor", b"b", -1, capacity=2, now=101.0)
    reg.hello("actor", second, b"b", "h", 2)
    assert second == 1
    with pytest.raises(NoSlot, match="all 2 actor numbers.*--actors"):
        reg.assign("actor", b"c", -1, capacity=2, now=time.time())
    with pytest.raises(NoSlot, match="actor number 2 is outside.*--actors 3"):
        reg.assign("actor", b"c", 2, capacity=2)
    reg.roles[("actor", 0)].last_seen -= 60  # actor 0 died: its number is free again
    assert reg.assign("actor", b"c", -1, capacity=2) == 0
    reg.hello("actor", 0, b"c", "h", 3)
    assert reg.seen(b"a") is None  # the dead holder's connection no longer speaks for number 0
    assert [row["id"] for row in reg.table(0) if row["role"] == "actor"] == [0, 1]  # no ghost rows
    assert reg.assign("dashboard", b"d", -1, capacity=None) == 0  # dashboards: as many as come


def test_a_role_silent_for_less_than_the_grace_keeps_its_number():
    from higher_dist.config import ConfigError
    from higher_dist.config_presets import make_config

    cfg = make_config("her", "small")
    reg = RoleRegistry(dead_after_s=cfg.role_grace_s)
    cut = reg.hello("actor", 0, b"a0", "host", 11)
    cut.last_seen -= 13.0  # a 10-second link cut and 3 s of reconnect
    assert reg.table(0)[0]["state"] == "alive"
    assert reg.assign("actor", b"newcomer", -1, capacity=2) == 1  # not number 0: its holder is in its grace
    cut.last_seen -= cfg.role_grace_s  # silent past the grace: dead, and its number is free again
    assert reg.table(0)[0]["state"] == "dead"
    assert reg.assign("actor", b"newcomer", -1, capacity=2) == 0
    with pytest.raises(ConfigError, match="role_grace_s"):
        make_config("her", "small", role_grace_s=1.0)
