"""Shared pytest setup: every ROS context in the test process stays on loopback, over UDP.

``make test`` runs the suite on two pytest-xdist workers, one per core: a third kept the cores busier
but did not finish sooner, and the 1 kHz simulators it ran beside fell further behind real time
(docs/measurements.md). Each worker gets its own range of
ROS domain ids; a test module stays on one worker (module fixtures are built once); the modules that
start franky-sim (127.0.0.1's libfranka ports) share one worker. The longest modules start first so
that no worker is left with a long tail.
Tests marked ``timing`` (1 kHz loops between processes, judged by the wall clock) are not run
beside anything: ``make test`` runs them serially after the rest.
"""

import os
from pathlib import Path

import pytest

from nf_bringup.processes import isolate

isolate(os.environ, domain_id=None, sources=False)

_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")  # gw0, gw1, ... under xdist
if _WORKER.startswith("gw"):
    # ROS domain ids 1..232 split into one disjoint range per worker
    _n, _width = int(_WORKER[2:]), 232 // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "2"))
    os.environ["NF_DOMAIN_IDS"] = f"{1 + _width * _n}-{_width * (_n + 1) - 1}"

# modules that start franky-sim (fixed ports on 127.0.0.1): one worker for all; the network-namespace
# tests (their own loopbacks, no franky-sim) form another unit, free to run beside them
_ONE_MACHINE = ("test_franka_", "test_robot_run", "test_thread_priority")
# the longest modules (seconds each, serial), started first
_FIRST = ("test_stability", "test_learning_over_ros", "test_franka_ros", "test_many_arms", "test_bags",
          "test_franka_gear")


def _scope(nodeid: str) -> str:
    module = nodeid.split("::", 1)[0]
    return "one_machine" if Path(module).stem.startswith(_ONE_MACHINE) else module


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))  # stable: file order otherwise


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """Work units of one module each, except the one-machine modules, which form one unit."""
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _scope(nodeid)

    return ModuleScheduling(config, log)


@pytest.fixture
def ros_args(monkeypatch):
    """``rclpy.init`` of this process with these ``--ros-args`` (as node ``sim_bridge``'s command line)
    in a domain of the test's own, shut down afterwards."""
    import sys

    import rclpy

    from nf_core import ros_runtime

    from ros_testing import allocate_domain_id

    monkeypatch.setenv("ROS_DOMAIN_ID", str(allocate_domain_id()))
    inited = []

    def init(*args: str) -> None:
        argv = ["sim_bridge", "--ros-args", *args]
        monkeypatch.setattr(sys, "argv", argv)
        monkeypatch.setattr(ros_runtime, "_command_line", None)
        rclpy.init(args=argv)
        inited.append(True)

    yield init
    if inited and rclpy.ok():
        rclpy.shutdown()
