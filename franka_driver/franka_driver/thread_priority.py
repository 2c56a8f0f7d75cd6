"""libfranka and the calling thread's scheduling. ROS-free.

What libfranka does (pylibfranka 0.21.3, checked on this machine: ``tests/test_thread_priority.py``):
its ``Robot`` constructor puts the *calling* thread at SCHED_FIFO 99 whenever the system allows
it, with ``RealtimeConfig.kIgnore`` too (``kEnforce`` also needs a realtime kernel). The driver
builds its ``Robot`` on the thread that builds the node, which then runs the ROS executor, and
every thread or process started from a SCHED_FIFO thread inherits it: left alone, the executor,
the loop thread and (in a test or benchmark process) every child process would run at FIFO 99.
So the driver opens the robot with ``open_robot`` (the caller's scheduling is given back) and
gives the loop thread its priority explicitly (``rt_priority``, -1 auto = FIFO 99, required with
``realtime: enforce``, taken if allowed with ``ignore``: ``nf_controller_node.thread_priority``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def open_robot(make: Callable[[], T]) -> T:
    """``make()`` (libfranka's ``Robot(...)``), then the calling thread's scheduling as it was before:
    the constructor's SCHED_FIFO 99 stays off the executor thread and everything started from it."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        return make()
    finally:
        os.sched_setscheduler(0, policy, param)
