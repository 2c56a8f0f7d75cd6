"""Realtime (SCHED_FIFO) priority for the torque loop's thread. ROS-free.

libfranka's callback API (``Robot::control``) puts its own control thread at the highest
SCHED_FIFO priority when the robot is opened with ``RealtimeConfig.kEnforce``; its active-control
API (``start_torque_control`` -> ``readOnce`` / ``writeOnce``), which this driver uses from Python,
does not touch the calling thread. So the driver does it itself, on the loop's thread only (the
executor and the DDS threads keep normal scheduling):

- ``rt_priority`` -1 (auto): the highest FIFO priority with ``realtime: enforce`` (as libfranka's
  own loops), normal scheduling with ``realtime: ignore``;
- 1..99: that FIFO priority; 0: normal scheduling.

A priority that cannot be had (no ``rtprio`` limit for the user, no CAP_SYS_NICE) is an error at
start-up, never a silent fall-back to normal scheduling.
"""

from __future__ import annotations

import os
import threading

AUTO = -1


def resolve_priority(requested: int, realtime_enforced: bool) -> int:
    """The FIFO priority to use (0: normal scheduling) for parameter value ``requested``."""
    if requested == AUTO:
        return os.sched_get_priority_max(os.SCHED_FIFO) if realtime_enforced else 0
    top = os.sched_get_priority_max(os.SCHED_FIFO)
    if not 0 <= requested <= top:
        raise ValueError(f"rt_priority must be -1 (auto), 0 (normal scheduling) or 1..{top}, got {requested}")
    return requested


def set_current_thread_priority(priority: int) -> None:
    """Put the calling thread at SCHED_FIFO ``priority`` (0: leave its scheduling alone). Raises
    OSError when the system refuses."""
    if priority > 0:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # 0: this thread (Linux)


def current_thread_policy() -> tuple[str, int]:
    """("fifo" | "other" | ..., priority) of the calling thread."""
    policy = os.sched_getscheduler(0)
    names = {os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr", os.SCHED_OTHER: "other"}
    return names.get(policy, str(policy)), os.sched_getparam(0).sched_priority


def check_priority_allowed(priority: int) -> str:
    """"" when a thread of this process may run at FIFO ``priority``, else why not. Tried on a
    short-lived thread, so no thread that stays keeps it."""
    if priority <= 0:
        return ""
    error: list[str] = []

    def probe() -> None:
        try:
            set_current_thread_priority(priority)
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
