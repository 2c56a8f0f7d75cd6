"""Test side of the process helper (``nf_bringup.processes``): child processes also import the test
modules (peers, samples); and the scheduling of a process's threads."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from nf_bringup import processes
from nf_bringup.processes import allocate_domain_id  # noqa: F401  (re-exported for the tests)

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"


def ros_env(domain_id: int, **extra: str) -> dict[str, str]:
    """``processes.ros_env`` with the tests folder importable too."""
    return processes.ros_env(domain_id, paths=(TESTS,), **extra)


class RosProcess(processes.RosProcess):
    """``processes.RosProcess`` with the tests folder importable too."""

    def __init__(self, args: Sequence[str], domain_id: int, log_path: Path | None = None, prefix: Sequence[str] = (),
                 peers: Sequence[str] = (), **extra: str) -> None:
        super().__init__(args, domain_id, log_path, prefix, paths=(TESTS,), peers=peers, **extra)


def thread_policies(pid: int) -> dict[int, int]:
    """Scheduling policy (``os.SCHED_*``) of every thread of process ``pid``, by thread id."""
    out = {}
    for tid in map(int, os.listdir(f"/proc/{pid}/task")):
        try:
            out[tid] = os.sched_getscheduler(tid)
        except OSError:  # the thread ended meanwhile
            pass
    return out
