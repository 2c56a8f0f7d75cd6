"""The 1 kHz loop thread's realtime priority (``nf_core.thread_priority``, the drivers'
``rt_priority``): libfranka's ``Robot()`` puts its calling thread at SCHED_FIFO 99 (checked here
against franky-sim) and ``open_robot`` gives it back; the priority is resolved from the parameter,
set by the kernel on the loop's thread only, and refused with a clear error (exit 2, before any
robot connection) when the system will not give it. The refusal is the kernel's own: the node runs
without CAP_SYS_NICE (``setpriv``) or as a user without an rtprio limit."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time

import pytest

from nf_core.thread_priority import (
    AUTO,
    apply,
    check_priority_allowed,
    current_thread_policy,
    enter_loop_thread,
    open_robot,
    resolve_priority,
)

from ros_testing import REPO, RosProcess, allocate_domain_id

TOP = os.sched_get_priority_max(os.SCHED_FIFO)
ALLOWED = check_priority_allowed(10) == ""


def _without_sys_nice() -> list[str] | None:
    """A command prefix that starts a child at normal scheduling without the realtime privilege
    (None if not possible here)."""
    chrt = shutil.which("chrt")
    if chrt is None:
        return None
    normal = [chrt, "--other", "0"]  # a child of a FIFO thread would inherit FIFO, and may always lower it
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        return [*normal, setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice"] if setpriv else None
    return normal if not ALLOWED else None  # a user without an rtprio limit is refused as it is


def test_auto_follows_realtime_and_explicit_values_are_checked():
    assert resolve_priority(AUTO, realtime_enforced=True) == (TOP, True)  # as libfranka: 99, or an error
    # realtime ignore: FIFO when the system allows it (as libfranka's kIgnore), else normal, never an error
    assert resolve_priority(AUTO, realtime_enforced=False) == ((TOP, False) if ALLOWED else (0, False))
    assert resolve_priority(0, True) == (0, False) and resolve_priority(20, False) == (20, True)
    for bad in (-2, TOP + 1, 1000):
        with pytest.raises(ValueError, match="rt_priority must be -1"):
            resolve_priority(bad, True)
    assert check_priority_allowed(0) == ""  # normal scheduling needs nothing


@pytest.mark.skipif(not ALLOWED, reason="this user may not use SCHED_FIFO (no rtprio limit)")
def test_the_priority_is_set_on_the_calling_thread_only():
    seen: list[tuple[str, int]] = []

    def loop_thread() -> None:
        apply(10)
        seen.append(current_thread_policy())
        inner: list[tuple[str, int]] = []
        child = threading.Thread(target=lambda: (inner.append(current_thread_policy()), apply(0),
                                                 inner.append(current_thread_policy())))
        child.start()
        child.join()
        seen.extend(inner)

    before = current_thread_policy()
    thread = threading.Thread(target=loop_thread)
    thread.start()
    thread.join()
    # a thread started from a FIFO thread inherits FIFO (why the driver sets every policy explicitly),
    # and apply(0) gives it normal scheduling back
    assert seen == [("fifo", 10), ("fifo", 10), ("other", 0)]
    assert current_thread_policy() == before  # the thread that started them kept its own


def test_the_kernel_refusing_fifo_gives_a_message_that_says_what_to_do():
    prefix = _without_sys_nice()
    if prefix is None:
        pytest.skip("cannot take the realtime privilege away from a child process here")
    source = str(REPO / "nf_core")
    code = (f"import sys; sys.path.insert(0, {source!r}); "
            "from nf_core.thread_priority import check_priority_allowed, enter_loop_thread; "
            "print(check_priority_allowed(10)); print(enter_loop_thread(10))")
    out = subprocess.run([*prefix, sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "cannot run the torque loop at SCHED_FIFO priority 10" in out.stdout, out.stdout
    assert "rtprio" in out.stdout and "rt_priority:=0" in out.stdout, out.stdout
    # a refusal as the loop thread starts (after a check that passed) leaves it at normal scheduling, said so
    assert "('other 0', 'SCHED_FIFO 10 refused: [Errno 1] Operation not permitted')" in out.stdout, out.stdout


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
    args = ["-m", "nf_bringup.franka_stack", "--ros-args", "--params-file", str(REPO / "config" / "franka.yaml"),
            "-p", "franka_driver:robot_ip:=127.0.0.1", *extra]  # no robot there: the check comes first
    with RosProcess(args, allocate_domain_id(), tmp_path / "stack.log", prefix=prefix) as stack:
        stack.proc.wait(60.0)
    assert stack.proc.returncode == 2 and reason in stack.log(), stack.log()
    assert "cannot connect" not in stack.log()


@pytest.mark.skipif(not ALLOWED, reason="this user may not use SCHED_FIFO (no rtprio limit)")
def test_libfranka_raises_its_callers_priority_and_open_robot_gives_it_back(tmp_path):
    """What the driver works around, on the real library: ``Robot()`` with ``kIgnore`` leaves the
    thread that called it at SCHED_FIFO 99 (the executor thread, and then every thread and process it
    starts); ``open_robot`` restores the caller's scheduling and the connection works as before."""
    pylibfranka = pytest.importorskip("pylibfranka")
    from nf_bringup.testing.franky import HOST, FrankySim

    out: dict[str, object] = {}

    def caller() -> None:  # a thread of its own: this test's thread keeps its scheduling either way
        apply(0)
        robot = pylibfranka.Robot(HOST, pylibfranka.RealtimeConfig.kIgnore)
        out["bare"] = current_thread_policy()
        del robot
        apply(0)
        robot = open_robot(lambda: pylibfranka.Robot(HOST, pylibfranka.RealtimeConfig.kIgnore))
        out["opened"] = current_thread_policy()
        out["q"] = list(robot.read_once().q)

    with FrankySim(tmp_path / "franky-sim.log"):
        thread = threading.Thread(target=caller)
        thread.start()
        thread.join(60.0)
    assert out["bare"] == ("fifo", TOP), out
    assert out["opened"] == ("other", 0) and len(out["q"]) == 7, out


@pytest.mark.ros
@pytest.mark.parametrize(("priority", "expected", "code"), [
    ("10", "cannot run the composed realtime loop at SCHED_FIFO priority 10", 2),  # asked for: refused
    ("-1", "driver thread (realtime): scheduling other 0", 0),  # auto: normal scheduling, said so
])
def test_the_composed_realtime_sim_takes_a_priority_only_where_the_system_gives_it(priority, expected, code,
                                                                                    tmp_path):
    prefix = _without_sys_nice()
    if prefix is None:
        pytest.skip("cannot take the realtime privilege away from a child process here")
    args = ["-m", "nf_bringup.sim_stack", "--ros-args", "-p", "sim_bridge:task:=free",
            "-p", "sim_bridge:mode:=realtime", "-p", f"sim_bridge:rt_priority:={priority}",
            "-p", "nf_controller:idle_mode:=hold"]
    with RosProcess(args, allocate_domain_id(), tmp_path / "stack.log", prefix=prefix) as stack:
        if code:  # refused: the process ends by itself
            stack.proc.wait(60.0)
        deadline = time.monotonic() + 60.0
        while stack.alive() and expected not in stack.log() and time.monotonic() < deadline:
            time.sleep(0.1)
        returncode = stack.stop() if stack.alive() else stack.proc.returncode
    assert returncode == code and expected in stack.log(), stack.log()


def test_the_loop_thread_says_how_it_runs_and_why_a_priority_did_not_take():
    out: list[tuple[str, str]] = []
    thread = threading.Thread(target=lambda: out.append(enter_loop_thread(0)))
    thread.start()
    thread.join()
    assert out == [("other 0", "")]
    if ALLOWED:
        thread = threading.Thread(target=lambda: out.append(enter_loop_thread(10)))
        thread.start()
        thread.join()
        assert out[-1] == ("fifo 10", "")
