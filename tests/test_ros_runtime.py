"""``ros_runtime.run_node``: a node's ``spin_pause`` bounds how often the executor resumes a coroutine
that waits (rclpy 7.1 resumes it again at once, so without a pause the executor thread spins and,
in a composed process, takes the GIL from the driver's tick); a ``SpinLock`` caller gets in between
spin slices. Real rclpy, own ROS_DOMAIN_ID."""

from __future__ import annotations

import sys
import threading
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

from nf_core import ros_runtime
from nf_core.ros_runtime import SpinLock, command_line_parameters, declare_read_only, run_node

from ros_testing import allocate_domain_id

WAIT = 0.5  # s the coroutine waits
PAUSE = 0.002  # s, spin_pause of the polite node


class _Yield:
    """Awaitable that gives control back to the executor once."""

    def __await__(self):
        yield


class _Waiter(Node):
    def __init__(self, pause: float) -> None:
        super().__init__("waiter")
        self.pause = pause
        self.resumes = 0
        self.finished = threading.Event()

    def spin_pause(self) -> float:
        return self.pause

    async def wait(self) -> None:
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            self.resumes += 1
            await _Yield()
        self.finished.set()


def _resumes(pause: float) -> int:
    made: list[_Waiter] = []

    def make() -> _Waiter:
        made.append(_Waiter(pause))
        return made[0]

    def started(nodes: list[Node]) -> None:
        nodes[0].executor.create_task(nodes[0].wait())

    def work(node: Node, stop: threading.Event) -> int:
        assert made[0].finished.wait(10.0), "the coroutine never finished"
        return 0

    assert run_node(make, "waiter", "test", ["waiter"], work=work, started=started) == 0
    return made[0].resumes


@pytest.fixture
def domain(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(allocate_domain_id()))


def test_spin_pause_bounds_how_often_a_waiting_coroutine_is_resumed(domain):
    polite = _resumes(PAUSE)
    assert polite <= WAIT / PAUSE + 50, f"{polite} resumes in {WAIT} s with a {PAUSE * 1e3:.0f} ms pause"
    busy = _resumes(0.0)  # what rclpy does by itself: the reason for spin_pause
    assert busy > 5 * polite, f"without a pause only {busy} resumes (with: {polite})"


class _Locked(Node):
    """An idle node (no work ends a slice early) with a spin lock."""

    def __init__(self) -> None:
        super().__init__("spin_lock_test")
        self.spin_lock = SpinLock()


@pytest.mark.parametrize("executor_kind", [SingleThreadedExecutor, EventsExecutor])
def test_a_spin_lock_caller_gets_in_without_waiting_out_the_slice(domain, monkeypatch, executor_kind):
    """``run_node`` with a main-thread ``work`` spins in slices that hold the node's ``SpinLock``;
    here the slices are 0.5 s long, so a caller that cannot end the executor's wait waits out the
    rest of one. Each turn comes 20 ms after the last, inside a fresh slice, and is timed on its own:
    with ``executor.wake()`` as the wake-up a turn took the rest of its slice (rclpy's executors went
    back to waiting: 98 ms median with 0.1 s slices); the slice's turn future ends the wait at once."""
    monkeypatch.setattr(ros_runtime, "WORK_SPIN_SLICE", 0.5)
    waits: list[float] = []

    def work(node: _Locked, stop: threading.Event) -> int:
        time.sleep(0.1)
        for _ in range(10):
            time.sleep(0.02)
            t0 = time.monotonic()
            with node.spin_lock:
                waits.append(time.monotonic() - t0)
        return 0

    assert run_node(_Locked, "locked", "test", ["locked"], work=work, make_executor=executor_kind) == 0
    waits.sort()
    assert waits[len(waits) // 2] < 0.05, f"median wait {waits[len(waits) // 2] * 1e3:.1f} ms with 0.5 s slices"
    assert waits[-1] < 0.3, f"a turn waited {waits[-1] * 1e3:.1f} ms with 0.5 s slices"


def test_command_line_parameters_that_reach_a_node():
    argv = ["prog", "--ros-args", "--params-file", "f.yaml", "-p", "franka_driver:a:=1", "-p", "b:=x",
            "-p", "sim_bridge:c:=2", "--param", "/franka_driver:d:=[1, 2]", "--", "-p", "e:=3"]
    assert command_line_parameters(argv, "franka_driver") == {"a": "1", "b": "x", "d": "[1, 2]"}
    assert command_line_parameters(argv, "sim_bridge") == {"b": "x", "c": "2"}


def test_a_command_line_value_the_parameters_file_kept_is_an_error(tmp_path, monkeypatch):
    """Real rcl: with the same parameter in a --params-file, a -p of another type is dropped without a
    word (the file's value stays); declare_read_only says so instead. Values rcl applies pass."""
    params = tmp_path / "p.yaml"
    params.write_text("probe_node:\n  ros__parameters:\n    settle: 200\n    gain: 1.5\n    goal: [0.0]\n")
    specs = {"settle": (100, ""), "gain": (1.0, ""), "goal": ([0.0], "")}
    cases = [(["-p", "probe_node:settle:=abc"], "-p probe_node:settle:=abc (in effect: 200)"),
             (["-p", "probe_node:gain:=1e-3", "-p", "goal:=[0.5,0.0,0.05]"], None)]
    for extra, error in cases:
        argv = ["prog", "--ros-args", "--params-file", str(params), *extra]
        monkeypatch.setattr(sys, "argv", argv)
        monkeypatch.setattr(ros_runtime, "_command_line", None)  # what a node made outside run_node sees
        context = rclpy.Context()
        rclpy.init(args=argv, context=context)
        node = Node("probe_node", context=context)
        try:
            if error is None:
                values = declare_read_only(node, specs)
                assert values["gain"] == 1e-3 and values["goal"] == [0.5, 0.0, 0.05] and values["settle"] == 200
            else:
                with pytest.raises(ValueError, match="not applied") as info:
                    declare_read_only(node, specs)
                assert error in str(info.value)
        finally:
            node.destroy_node()
            rclpy.shutdown(context=context)
