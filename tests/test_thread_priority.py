"""The torque loop thread's realtime priority (``franka_driver.thread_priority``, the driver's
``rt_priority``): resolved from the parameter, really set by the kernel on the loop's thread only,
and refused with a clear error (exit 2, before any robot connection) when the system will not give it.
The refusal is the kernel's own: the node runs without CAP_SYS_NICE (``setpriv``) or as a user
without an rtprio limit."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading

import pytest

from franka_driver.thread_priority import (
    AUTO,
    check_priority_allowed,
    current_thread_policy,
    resolve_priority,
    set_current_thread_priority,
)

from ros_testing import REPO, RosProcess, allocate_domain_id

TOP = os.sched_get_priority_max(os.SCHED_FIFO)
ALLOWED = check_priority_allowed(10) == ""


def _without_sys_nice() -> list[str] | None:
    """A command prefix that takes the realtime privilege away from a child (None if not possible here)."""
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        return [setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice"] if setpriv else None
    return [] if not ALLOWED else None  # a user without an rtprio limit is refused as it is


def test_auto_follows_realtime_and_explicit_values_are_checked():
    assert resolve_priority(AUTO, realtime_enforced=True) == TOP  # as libfranka's own control loops
    assert resolve_priority(AUTO, realtime_enforced=False) == 0
    assert resolve_priority(0, True) == 0 and resolve_priority(20, False) == 20
    for bad in (-2, TOP + 1, 1000):
        with pytest.raises(ValueError, match="rt_priority must be -1"):
            resolve_priority(bad, True)
    assert check_priority_allowed(0) == ""  # normal scheduling needs nothing


@pytest.mark.skipif(not ALLOWED, reason="this user may not use SCHED_FIFO (no rtprio limit)")
def test_the_priority_is_set_on_the_calling_thread_only():
    seen: list[tuple[str, int]] = []

    def loop_thread() -> None:
        set_current_thread_priority(10)
        seen.append(current_thread_policy())

    thread = threading.Thread(target=loop_thread)
    thread.start()
    thread.join()
    assert seen == [("fifo", 10)]
    assert current_thread_policy() == ("other", 0)  # this (main) thread kept normal scheduling


def test_the_kernel_refusing_fifo_gives_a_message_that_says_what_to_do():
    prefix = _without_sys_nice()
    if prefix is None:
        pytest.skip("cannot take the realtime privilege away from a child process here")
    source = str(REPO / "franka_driver")
    code = (f"import sys; sys.path.insert(0, {source!r}); "
            "from franka_driver.thread_priority import check_priority_allowed; print(check_priority_allowed(10))")
    out = subprocess.run([*prefix, sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "cannot run the torque loop at SCHED_FIFO priority 10" in out.stdout, out.stdout
    assert "rtprio" in out.stdout and "rt_priority:=0" in out.stdout, out.stdout


@pytest.mark.ros
@pytest.mark.parametrize(("extra", "reason", "unprivileged"), [
    (["-p", "franka_driver:realtime:=ignore", "-p", "franka_driver:rt_priority:=150"],
     "rt_priority must be -1", False),
    # the hardware file's defaults (realtime enforce, rt_priority auto) on a machine that gives no
    # realtime priority: a clear refusal before connecting, not a loop at normal priority
    ([], "cannot run the torque loop at SCHED_FIFO priority", True),
    (["-p", "franka_driver:realtime:=ignore", "-p", "franka_driver:rt_priority:=10"],
     "cannot run the torque loop at SCHED_FIFO priority 10", True),
])
def test_the_driver_refuses_a_priority_it_cannot_have_before_connecting(extra, reason, unprivileged, tmp_path):
    prefix: list[str] = []
    if unprivileged:
        prefix = _without_sys_nice()
        if prefix is None:
            pytest.skip("cannot take the realtime privilege away from a child process here")
    args = ["-m", "franka_driver.stack", "--ros-args", "--params-file", str(REPO / "config" / "franka.yaml"),
            "-p", "franka_driver:robot_ip:=127.0.0.1", *extra]  # no robot there: the check comes first
    with RosProcess(args, allocate_domain_id(), tmp_path / "stack.log", prefix=prefix) as stack:
        stack.proc.wait(60.0)
    assert stack.proc.returncode == 2 and reason in stack.log(), stack.log()
    assert "cannot connect" not in stack.log()
