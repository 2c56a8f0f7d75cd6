"""Helpers for tests that start ROS 2 processes: isolated domain IDs, loopback-only discovery,
child processes started and stopped by PID."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_counter = itertools.count()
# The tests kill processes with SIGKILL on purpose (recorder, learner, controller, robot). Fast DDS's
# shared-memory transport keeps per-process segments and locks in /dev/shm that a killed process
# leaves behind (hundreds after one suite), and a peer blocked inside such a segment waits in C++,
# where neither pytest-timeout's alarm nor anything else reaches it: a fresh-clone CI run once hung
# for 80 minutes in the first test after the kills. Every ROS process of the tests, the test process
# included (conftest.py), therefore talks over UDP on loopback only.
TEST_TRANSPORTS = "UDPv4"


def allocate_domain_id() -> int:
    """A ROS_DOMAIN_ID for one test: distinct per test in this run, spread by PID across runs."""
    return 1 + (os.getpid() * 7 + next(_counter)) % 200


def ros_env(domain_id: int, **extra: str) -> dict[str, str]:
    """Environment for a ROS process: its own domain, discovery on loopback only."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_STATIC_PEERS", None)
    env["FASTDDS_BUILTIN_TRANSPORTS"] = TEST_TRANSPORTS
    env["PYTHONUNBUFFERED"] = "1"
    packages = ("nf_core", "nf_controller_node", "learner_node", "sim_bridge_node", "nf_bringup", "franka_driver",
                "bags", "tests")
    paths = [str(REPO / p) for p in packages]
    env["PYTHONPATH"] = os.pathsep.join([*paths, env.get("PYTHONPATH", "")])
    env.update(extra)
    return env


def thread_policies(pid: int) -> dict[int, int]:
    """Scheduling policy (``os.SCHED_*``) of every thread of process ``pid``, by thread id."""
    out = {}
    for tid in map(int, os.listdir(f"/proc/{pid}/task")):
        try:
            out[tid] = os.sched_getscheduler(tid)
        except OSError:  # the thread ended meanwhile
            pass
    return out


class RosProcess:
    """A child Python process in a given ROS domain; stopped (SIGINT, then SIGKILL) by its PID.
    ``prefix``: a command that execs Python in its own place (``setpriv ...``: same PID)."""

    def __init__(self, args: Sequence[str], domain_id: int, log_path: Path | None = None,
                 prefix: Sequence[str] = (), **extra: str):
        self.log_path = log_path
        out = open(log_path, "w") if log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(
            [*prefix, sys.executable, *args], env=ros_env(domain_id, **extra), stdout=out, stderr=subprocess.STDOUT
        )

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int:
        """Interrupt the process and wait; kill it if it does not exit in time. Returns its exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        return self.proc.returncode

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path and self.log_path.exists() else ""

    def __enter__(self) -> RosProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
