"""Hosts for the multi-host tests: Linux network namespaces on a bridge, the bridge in a namespace of its
own, so nothing of the machine's own network is touched. Needs root and iproute2 (`ip netns`).

    hd<tag>-br    bridge br0, one port (veth) per host
    hd<tag>-NAME  one namespace per host, its veth end `eth0` at 10.213.<subnet>.<k>/24
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time


def netns_unavailable() -> str | None:
    """Why network namespaces cannot be made here (a skip reason), or None."""
    if os.geteuid() != 0:
        return "needs root to create network namespaces (CI runs as root)"
    if shutil.which("ip") is None:
        return "iproute2's `ip` is not installed (make test installs it where apt-get is available)"
    probe = f"hdprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"`ip netns add` fails here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def ip(*args: str, ns: str | None = None) -> str:
    argv = ["ip", *(["-n", ns] if ns else []), *args]
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()}")
    return done.stdout


class Hosts:
    """Namespaces named `names` on one bridge; `addr(name)` is a host's address, `ns(name)` its namespace."""

    def __init__(self, names: list[str], tag: str | None = None):
        self.tag = tag or str(os.getpid() % 100_000)
        self.subnet = 20 + os.getpid() % 200
        self.bridge_ns = f"hd{self.tag}-br"
        self.names = list(names)
        self.made: list[str] = []
        try:
            self._build()
        except Exception:
            self.destroy()
            raise

    def ns(self, name: str) -> str:
        return f"hd{self.tag}-{name}"

    def addr(self, name: str) -> str:
        return f"10.213.{self.subnet}.{self.names.index(name) + 1}"

    def port(self, name: str) -> str:
        """The bridge's port of a host (down = the host's cable pulled)."""
        return f"p{self.names.index(name)}-{self.tag}"[:15]

    def _build(self) -> None:
        ip("netns", "add", self.bridge_ns)
        self.made.append(self.bridge_ns)
        ip("link", "add", "br0", "type", "bridge", ns=self.bridge_ns)
        ip("link", "set", "br0", "up", ns=self.bridge_ns)
        for name in self.names:
            ns = self.ns(name)
            ip("netns", "add", ns)
            self.made.append(ns)
            host_end, bridge_end = f"h{self.names.index(name)}-{self.tag}"[:15], self.port(name)
            ip("link", "add", host_end, "type", "veth", "peer", "name", bridge_end)
            ip("link", "set", host_end, "netns", ns, "name", "eth0")
            ip("link", "set", bridge_end, "netns", self.bridge_ns)
            ip("link", "set", bridge_end, "master", "br0", "up", ns=self.bridge_ns)
            ip("addr", "add", f"{self.addr(name)}/24", "dev", "eth0", ns=ns)
            ip("link", "set", "eth0", "up", ns=ns)
            ip("link", "set", "lo", "up", ns=ns)
        deadline = time.monotonic() + 10  # a fresh bridge port may take a moment to forward
        while time.monotonic() < deadline:
            if self.reachable(self.names[0], self.addr(self.names[-1])):
                return
            time.sleep(0.2)
        raise RuntimeError("the namespaces cannot reach each other over the bridge")

    def reachable(self, src: str, dst_addr: str) -> bool:
        """A TCP connect from `src` to a closed port of `dst_addr` is refused (reachable) or times out."""
        probe = ("import socket,sys\ntry: socket.create_connection((sys.argv[1], 9), 1)\n"
                 "except ConnectionRefusedError: sys.exit(0)\nexcept OSError: sys.exit(1)")
        return subprocess.run(self.exec_argv(src, [sys.executable, "-c", probe, dst_addr]),
                              capture_output=True).returncode == 0

    def link(self, name: str, up: bool) -> None:
        ip("link", "set", self.port(name), "up" if up else "down", ns=self.bridge_ns)

    def exec_argv(self, name: str, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.ns(name), *argv]

    def destroy(self) -> None:
        for ns in reversed(self.made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.made.clear()
