"""The learner's view of the other roles: who said hello, when each was last heard, what it reports.

A role silent for longer than `dead_after_s` is marked dead (the launcher restarts crashed processes;
this table is what the dashboard shows). Pure bookkeeping: no sockets.

Numbers (an actor's number sets its epsilon): a role asking for a fixed number gets it if it is inside
the run's count for that role, and takes over the entry (a supervisor restarting "actor 3" means it). A
role asking for any number keeps the one its connection already has (a repeated hello), else gets the
lowest number whose holder is dead or stopped; when every number is held by a live role it is refused.
The count does not grow: actors cannot join beyond the learner's --actors, because each actor's epsilon
is placed among that many.

`telemetry` folds the table into the record's cluster-wide fields (frames/s, weights lag, epsilon, the
relabeler's numbers, rejects by reason over every role).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from higher_dist import metrics as m

# A role's dropped messages travel in its stats as reject_<reason>: count; the learner sums them by reason.
REJECT_STAT_PREFIX = m.REJECT_STAT_PREFIX


@dataclass
class RoleInfo:
    role: str
    id: int
    identity: bytes
    host: str = ""
    pid: int = 0
    last_seen: float = field(default_factory=time.time)
    state: str = "alive"
    stats: dict[str, Any] = field(default_factory=dict)
    stopped: bool = False


class NoSlot(ValueError):
    """A hello that cannot be given a number; the message is the reason sent in the refusal."""


class RoleRegistry:
    def __init__(self, dead_after_s: float = 10.0):
        self.dead_after_s = dead_after_s
        self.roles: dict[tuple[str, int], RoleInfo] = {}
        self._by_identity: dict[bytes, tuple[str, int]] = {}

    def _live(self, info: RoleInfo, now: float) -> bool:
        return not info.stopped and now - info.last_seen <= self.dead_after_s

    def assign(self, role: str, identity: bytes, requested: int, capacity: int | None,
               now: float | None = None) -> int:
        """The number for a hello (see the module's docstring), or NoSlot with the reason."""
        now = time.time() if now is None else now
        flag = "--actors" if role == "actor" else None
        if requested >= 0:
            if capacity is not None and requested >= capacity:
                more = f"; start the learner with {flag} {requested + 1} or more" if flag else ""
                raise NoSlot(f"{role} number {requested} is outside this run's {capacity} {role}(s), "
                             f"numbered 0 to {capacity - 1}{more}")
            return requested
        key = self._by_identity.get(identity)
        if key is not None and key[0] == role and self.roles.get(key) is not None \
                and self.roles[key].identity == identity:
            return key[1]  # a repeated hello on the same connection keeps its number
        held = {i for (r, i), info in self.roles.items() if r == role and self._live(info, now)}
        limit = capacity if capacity is not None else len(held) + 1
        for index in range(limit):
            if index not in held:
                return index
        more = f"; start the learner with a larger {flag}" if flag else ""
        raise NoSlot(f"all {capacity} {role} numbers are held by live {role}s{more}")

    def hello(self, role: str, index: int, identity: bytes, host: str, pid: int) -> RoleInfo:
        key = (role, index)
        info = self.roles.get(key)
        if info is None or info.identity != identity:
            if info is not None:
                self._by_identity.pop(info.identity, None)  # the old holder of this number is replaced
            info = RoleInfo(role, index, identity, host, pid)
            self.roles[key] = info
        info.host, info.pid, info.last_seen, info.stopped = host, pid, time.time(), False
        self._by_identity[identity] = key
        return info

    def seen(self, identity: bytes) -> RoleInfo | None:
        key = self._by_identity.get(identity)
        info = self.roles.get(key) if key else None
        if info is not None:
            info.last_seen = time.time()
        return info

    def identities(self) -> list[bytes]:
        return [info.identity for info in self.roles.values() if not info.stopped]

    def table(self, learner_version: int, now: float | None = None) -> list[dict[str, Any]]:
        now = now or time.time()
        rows = []
        for (role, index), info in sorted(self.roles.items()):
            age = now - info.last_seen
            state = "stopped" if info.stopped else ("dead" if age > self.dead_after_s else "alive")
            info.state = state
            # A role's stats arrive from time to time: until its first, what it has not reported is None.
            version = info.stats.get(m.WEIGHTS_VERSION)
            rows.append({
                m.ROW_ROLE: role, m.ROW_ID: index, m.ROW_HOST: info.host, m.ROW_PID: info.pid, m.ROW_STATE: state,
                m.ROW_HEARTBEAT_AGE: round(age, 1), m.FRAMES_PER_S: info.stats.get(m.FRAMES_PER_S),
                m.ROW_WEIGHTS_LAG: None if version is None else max(learner_version - int(version), 0),
                m.ROW_RESTARTS: int(info.stats.get(m.ROW_RESTARTS, 0) or 0),
                m.ROW_REJECTED: int(info.stats.get(m.REJECTED, 0) or 0),
            })
        return rows

    def telemetry(self, own_row: dict[str, Any], learner_version: int,
                  own_rejects: dict[str, int]) -> dict[str, Any]:
        """The record's fields about the cluster: the role table (the learner's own row first) and what
        is summed or averaged over the roles. `own_rejects`: the learner's rejects by reason."""
        roles = [own_row] + self.table(learner_version)
        relabeler = next((i.stats for i in self.roles.values() if i.role == "relabeler"), {})
        actors = [i for i in self.roles.values() if i.role == "actor"]
        actor_rows = [row for row in roles if row[m.ROW_ROLE] == "actor"]
        actor_fps = [row[m.FRAMES_PER_S] or 0.0 for row in actor_rows if row[m.ROW_STATE] == "alive"]
        lags = [row[m.ROW_WEIGHTS_LAG] for row in actor_rows if row[m.ROW_WEIGHTS_LAG] is not None]
        eps = [i.stats[m.EPSILON_MEAN] for i in actors if i.stats.get(m.EPSILON_MEAN) is not None]
        by_reason = dict(own_rejects)
        for info in self.roles.values():
            for key, value in info.stats.items():
                if key.startswith(REJECT_STAT_PREFIX) and isinstance(value, (int, float)):
                    reason = key[len(REJECT_STAT_PREFIX):]
                    by_reason[reason] = by_reason.get(reason, 0) + int(value)
        return {
            m.FRAMES_PER_S: round(sum(actor_fps), 1),
            m.WEIGHTS_LAG_MEAN: round(float(np.mean(lags)), 1) if lags else None,
            m.REJECTED: sum(by_reason.values()), m.REJECTS_BY_REASON: by_reason,
            **{key: relabeler.get(key) for key in m.RELABELER_KEYS},
            m.EPSILON_MEAN: round(float(np.mean(eps)), 4) if eps else None,
            m.ROLES: roles,
        }


class RateMeter:
    """The rate of a growing counter, over windows of at least `min_window_s` (a shorter one, such as
    the final record's, keeps the last rate instead of reporting a meaningless one)."""

    def __init__(self, min_window_s: float = 0.25):
        self.min_window_s = min_window_s
        self.rate = 0.0
        self._since: tuple[float, float] | None = None

    def __call__(self, value: float, now: float | None = None) -> float:
        now = time.time() if now is None else now
        if self._since is None:
            self._since = (now, value)
        elif now - self._since[0] >= self.min_window_s:
            self.rate = (value - self._since[1]) / (now - self._since[0])
            self._since = (now, value)
        return self.rate

