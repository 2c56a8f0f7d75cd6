"""Two hosts on one machine: two Linux network namespaces joined by a veth pair, the stand-in for a
learner's machine and a robot PC on one subnet. Needs root (``ip netns``); everything it creates
is deleted on exit, and its traffic can only reach the two addresses it gives the namespaces.

    with TwoHosts() as hosts:                       # "a" = 10.231.<n>.1, "b" = 10.231.<n>.2
        RosProcess([...], domain, prefix=hosts.prefix("a"), peers=[hosts.address("b")])

A process is started in a host with ``ip netns exec <namespace>`` (it execs its command: the PID is
the process's own) and discovers its peers with ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` and
``ROS_STATIC_PEERS`` (unicast), as on two real machines.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Sequence

SUBNET = "10.231"  # a private range no other test or service of ours uses


class NetnsUnavailableError(RuntimeError):
    """This machine (or user) cannot create network namespaces."""


def _ip(*args: str, netns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    cmd = ["ip", *(["netns", "exec", netns, "ip"] if netns else []), *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr.strip()}")
    return done


class TwoHosts:
    """Namespaces ``nf-<tag>-a`` and ``nf-<tag>-b`` with one veth pair between them (/24, MTU 1500)."""

    def __init__(self, tag: str | None = None) -> None:
        self.tag = tag or str(os.getpid())
        n = 1 + int(self.tag) % 250 if self.tag.isdigit() else 1
        self.names = {"a": f"nf-{self.tag}-a", "b": f"nf-{self.tag}-b"}
        self.addresses = {"a": f"{SUBNET}.{n}.1", "b": f"{SUBNET}.{n}.2"}
        self._veth = (f"nfv{self.tag}a"[:15], f"nfv{self.tag}b"[:15])
        self._made: list[str] = []

    def prefix(self, host: str) -> list[str]:
        """The command prefix that runs a program in ``host`` ("a" or "b")."""
        return ["ip", "netns", "exec", self.names[host]]

    def address(self, host: str) -> str:
        """The IPv4 address of ``host`` on the link."""
        return self.addresses[host]

    def peers(self, host: str) -> Sequence[str]:
        """The unicast peers a process in ``host`` discovers (the other host)."""
        return [self.addresses[h] for h in self.names if h != host]

    def __enter__(self) -> TwoHosts:
        if os.geteuid() != 0:
            raise NetnsUnavailableError("network namespaces need root (ip netns add)")
        try:
            for name in self.names.values():
                done = _ip("netns", "add", name, check=False)
                if done.returncode != 0:
                    raise NetnsUnavailableError(f"ip netns add {name} refused: {done.stderr.strip()}")
                self._made.append(name)
            a, b = self._veth
            _ip("link", "add", a, "type", "veth", "peer", "name", b)
            for host, dev in zip(self.names, self._veth, strict=True):
                _ip("link", "set", dev, "netns", self.names[host])
                _ip("addr", "add", f"{self.addresses[host]}/24", "dev", dev, netns=self.names[host])
                _ip("link", "set", dev, "up", netns=self.names[host])
                _ip("link", "set", "lo", "up", netns=self.names[host])
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Delete both namespaces (their veth ends go with them)."""
        for name in self._made:
            _ip("netns", "delete", name, check=False)
        self._made.clear()
        _ip("link", "delete", self._veth[0], check=False)  # only if it never left this namespace

    def __exit__(self, *exc: object) -> None:
        self.close()
