"""Hostile effort commands against the sim bridge's ROS-free core (issue 16, items 4 and 5): a bad
command is counted with its reason kept (bounded) for the node's diagnostics timer to log once,
and never steps the world."""

from __future__ import annotations

import array

import numpy as np
import pytest

from sim_bridge_node.bridge import ACCEPTED, BAD, BridgeConfig, SimBridge
from sim_bridge_node.env import InsertionEnv


@pytest.fixture(scope="module")
def free_env() -> InsertionEnv:
    return InsertionEnv("free")


def _bridge(env: InsertionEnv, **kw) -> SimBridge:
    bridge = SimBridge(env, BridgeConfig(**kw))
    bridge.reset()
    return bridge


HOSTILE = {
    "20,000 values": (array.array("d", [0.0] * 20_000), "20000 values, expected 7"),
    "NaN": (array.array("d", [0.0] * 6 + [float("nan")]), "NaN/Inf for ['panda_joint7']"),
    "all inf": ([float("inf")] * 7, "NaN/Inf for"),
    "a 1 MB string": (["x" * 1_000_000] * 7, "not an array of numbers"),
    "nested": ([[1.0, 2.0]] * 7, "command has 14 values"),
    "a number": (3.0, "not an array of numbers"),
}


@pytest.mark.parametrize("mode", ["lockstep", "realtime"])
def test_bad_commands_are_counted_bounded_and_reported_once(free_env, mode):
    bridge = _bridge(free_env, mode=mode)
    assert bridge.take_error_report() is None and bridge.last_error == ""
    q, t = free_env.q.copy(), free_env.time
    for data, match in HOSTILE.values():
        assert bridge.accept_command(data, now=0.0) == BAD
        assert match in bridge.last_error and len(bridge.last_error) <= 300
    assert not bridge.has_command and not bridge.step_commanded()
    np.testing.assert_array_equal(free_env.q, q)
    assert free_env.time == t
    report = bridge.take_error_report()
    n = len(HOSTILE)
    assert report is not None and report.startswith(f"{n} bad effort command(s) ignored ({n} in all), last: ")
    assert len(report) <= 400 and bridge.take_error_report() is None, "reported once"
    assert bridge.accept_command(array.array("d", bridge.gravity().tolist()), now=0.0) == ACCEPTED
    assert bridge.take_error_report() is None and bridge.bad_commands == n


def test_check_command_still_raises_with_the_reason(free_env):
    bridge = _bridge(free_env)
    with pytest.raises(ValueError, match="command has 3 values, expected 7"):
        bridge.check_command([0.0] * 3)
    with pytest.raises(ValueError, match="NaN/Inf"):
        bridge.check_command([np.nan] * 7)
    assert bridge.bad_commands == 0 and bridge.last_error == "", "a direct check is not a rejected command"
    np.testing.assert_array_equal(bridge.check_command(range(7)), np.arange(7.0))


@pytest.mark.parametrize("gravity", [False, True])
def test_a_composed_controllers_bad_torque_never_steps_the_world(free_env, gravity):
    """``step_with`` (the composed lockstep's direct hand-over) checks what the command path checks:
    a NaN, an Inf or a wrong size is counted with its reason and the world does not move."""
    bridge = _bridge(free_env, mode="lockstep", driver_gravity_compensation=gravity)
    qpos, steps = free_env.data.qpos.copy(), bridge.steps
    for tau, reason in ((np.array([0.0] * 6 + [np.nan]), "NaN/Inf for ['panda_joint7']"),
                        (np.full(7, np.inf), "NaN/Inf for"), (np.zeros(9), "command has 9 values")):
        assert not bridge.step_with(tau)
        assert reason in bridge.last_error
    assert bridge.bad_commands == 3 and bridge.steps == steps
    np.testing.assert_array_equal(free_env.data.qpos, qpos)
    big = np.full(7, 1e6)  # finite: clamped to the actuator limits and applied
    assert bridge.step_with(big) and bridge.steps == steps + 1
    np.testing.assert_array_equal(bridge.torque, free_env.last_torque)
    assert np.all(bridge.torque <= free_env.model.actuator_ctrlrange[:, 1])


def test_a_composed_realtime_torque_is_checked_like_a_command(free_env):
    """``accept_torque`` (composed realtime) keeps a finite torque for the next ticks and refuses a
    NaN or a wrong size as ``accept_command`` does, keeping the last good one."""
    bridge = _bridge(free_env, mode="realtime")
    good = np.linspace(-1.0, 1.0, 7)
    assert bridge.accept_torque(good, 0.0) == ACCEPTED
    assert bridge.accept_torque(np.array([np.nan] * 7), 0.001) == BAD and "NaN/Inf" in bridge.last_error
    assert bridge.accept_torque(np.zeros(3), 0.002) == BAD and "3 values" in bridge.last_error
    assert bridge.bad_commands == 2
    assert not bridge.step_realtime(0.003)  # the good torque, not the safe hold
    np.testing.assert_allclose(bridge.torque, np.clip(good, *free_env.model.actuator_ctrlrange.T))
