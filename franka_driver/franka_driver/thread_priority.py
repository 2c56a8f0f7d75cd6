"""Realtime (SCHED_FIFO) priority of the torque loop's thread, and only of it. ROS-free.

What libfranka does (pylibfranka 0.21.3, checked on this machine: ``tests/test_thread_priority.py``):
its ``Robot`` constructor puts the *calling* thread at SCHED_FIFO 99 whenever the system allows
it, with ``RealtimeConfig.kIgnore`` too (``kEnforce`` also needs a realtime kernel). The driver
builds its ``Robot`` on the thread that builds the node, which then runs the ROS executor, and
every thread or process started from a SCHED_FIFO thread inherits it: left alone, the executor,
the loop thread and (in a test or benchmark process) every child process would run at FIFO 99.
So the driver opens the robot with ``open_robot`` (the caller's scheduling is given back) and
gives the loop thread its priority explicitly (``apply``):

- ``rt_priority`` -1 (auto): as libfranka's own loops: FIFO 99 with ``realtime: enforce`` (an
  error at start-up when the system refuses it), FIFO 99 if the system allows it with ``ignore``
  (normal scheduling otherwise);
- 1..99: that FIFO priority (an error at start-up when refused); 0: normal scheduling.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import TypeVar

AUTO = -1
T = TypeVar("T")


def top_priority() -> int:
    """The highest SCHED_FIFO priority (99 on Linux), the one libfranka gives its threads."""
    return os.sched_get_priority_max(os.SCHED_FIFO)


def resolve_priority(requested: int, realtime_enforced: bool) -> tuple[int, bool]:
    """(FIFO priority to use, 0 for normal scheduling; whether a refusal is an error) for the
    parameter value ``requested``. Auto with ``realtime: ignore`` takes FIFO only if allowed."""
    top = top_priority()
    if requested == AUTO:
        if realtime_enforced:
            return top, True
        return (top, False) if check_priority_allowed(top) == "" else (0, False)
    if not 0 <= requested <= top:
        raise ValueError(f"rt_priority must be -1 (auto), 0 (normal scheduling) or 1..{top}, got {requested}")
    return requested, requested > 0


def apply(priority: int) -> None:
    """Give the calling thread SCHED_FIFO ``priority``, or normal scheduling for 0 (also when it
    inherited FIFO from its creator). Raises OSError when the system refuses."""
    if priority > 0:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # 0: this thread (Linux)
    else:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # lowering is always allowed


def current_thread_policy() -> tuple[str, int]:
    """("fifo" | "other" | ..., priority) of the calling thread."""
    policy = os.sched_getscheduler(0)
    names = {os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr", os.SCHED_OTHER: "other"}
    return names.get(policy, str(policy)), os.sched_getparam(0).sched_priority


def open_robot(make: Callable[[], T]) -> T:
    """``make()`` (libfranka's ``Robot(...)``), then the calling thread's scheduling as it was before:
    the constructor's SCHED_FIFO 99 stays off the executor thread and everything started from it."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        return make()
    finally:
        os.sched_setscheduler(0, policy, param)


def check_priority_allowed(priority: int) -> str:
    """"" when a thread of this process may take SCHED_FIFO ``priority``, else why not. Tried on a
    short-lived thread that starts at normal scheduling, so no thread that stays keeps it (and a
    caller that runs at FIFO itself, whose threads inherit it, does not make it look allowed)."""
    if priority <= 0:
        return ""
    error: list[str] = []

    def probe() -> None:
        try:
            apply(0)
            apply(priority)
        except OSError as exc:
            error.append(f"{type(exc).__name__}: {exc}")

    thread = threading.Thread(target=probe, name="rt-priority-probe")
    thread.start()
    thread.join()
    if not error:
        return ""
    return (f"cannot run the torque loop at SCHED_FIFO priority {priority} ({error[0]}): give this user an "
            f"'rtprio' limit of at least {priority} (/etc/security/limits.conf; Franka's Linux setup guide does "
            f"this for its realtime group), or set rt_priority:=0 for normal scheduling")
