"""The learner's view of the other roles: who said hello, when each was last heard, what it reports.

A role silent for longer than `dead_after_s` is marked dead (the launcher restarts crashed processes;
this table is what the dashboard shows). Pure bookkeeping: no sockets.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any


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


class RoleRegistry:
    def __init__(self, dead_after_s: float = 10.0):
        self.dead_after_s = dead_after_s
        self.roles: dict[tuple[str, int], RoleInfo] = {}
        self._by_identity: dict[bytes, tuple[str, int]] = {}

    def next_index(self, role: str) -> int:
        taken = {i for (r, i) in self.roles if r == role}
        return next(i for i in range(len(taken) + 1) if i not in taken)

    def hello(self, role: str, index: int, identity: bytes, host: str, pid: int) -> RoleInfo:
        key = (role, index)
        info = self.roles.get(key)
        if info is None or info.identity != identity:
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
            version = info.stats.get("weights_version")
            rows.append({
                "role": role, "id": index, "host": info.host, "pid": info.pid, "state": state,
                "heartbeat_age_s": round(age, 1), "frames_per_s": info.stats.get("frames_per_s"),
                "weights_lag": None if version is None else max(learner_version - int(version), 0),
                "restarts": int(info.stats.get("restarts", 0) or 0),
                "rejected": int(info.stats.get("rejected_messages", 0) or 0),
            })
        return rows



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

