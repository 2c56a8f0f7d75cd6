"""Hostile input over real DDS (issue 16): a third process floods the realtime sim and the
standalone controller with malformed joint states, commands and policies, about one bad message
per millisecond. Every command the controller sends stays finite, within the torque limits and
within one rate-limit step of the previous one; the fault it latches clears; the realtime sim
keeps real time; nothing crashes."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from nf_bags import reader
from nf_msgs.msg import ControllerStatus, TaskStatus
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import qos
from nf_core.panda_spec import JOINT_NAMES, TORQUE_LIMITS
from nf_core.topics import POLICY_PARAMETERS

from ros_testing import RosProcess, allocate_domain_id
from test_nodes import RELIABLE, SIM, Probe, diag_values, policy_msg

pytestmark = pytest.mark.ros

ALL = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)  # every command, in order
MAX_STEP = TorqueLawConfig().max_step  # Nm per command (1000 Nm/s at 1 kHz)
Q_OK = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])


def _bad_states(n: int, rng: np.random.Generator) -> list[JointState]:
    """``n`` malformed joint states of seven kinds (the huge-name-list kind only a few times)."""
    out = []
    for i in range(n):
        kind = i % 7
        msg = JointState(name=list(JOINT_NAMES), position=Q_OK.tolist(), velocity=[0.0] * 7)
        msg.header.stamp = Time(sec=1, nanosec=0)
        if kind == 0:
            msg.position[rng.integers(7)] = float("nan")
        elif kind == 1:
            msg.position[rng.integers(7)] = 1e300
        elif kind == 2:
            msg.velocity[rng.integers(7)] = -1e6
        elif kind == 3:
            msg.header.stamp = Time(sec=2**31 - 1, nanosec=0)  # far future: must not poison the clock
        elif kind == 4:
            msg.position = msg.position[:5]
        elif kind == 5:
            msg.name = [*JOINT_NAMES[:6], "panda_joint1"]
        else:
            msg.name = [f"j{k}" for k in range(20_000 if i < 21 else 9)]
            msg.position = [0.0] * len(msg.name)
            msg.velocity = [0.0] * len(msg.name)
        out.append(msg)
    return out


def _bad_commands(n: int) -> list[Float64MultiArray]:
    out = []
    for i in range(n):
        data = [0.0] * (7 if i % 3 else 4)
        if i % 3 == 1:
            data[i % 7] = float("nan")
        elif i % 3 == 2:
            data[i % 7] = float("-inf")
        out.append(Float64MultiArray(data=data))
    return out


def _bad_policies(x_ref: np.ndarray) -> list[PolicyParametersMsg]:
    out = []
    for version in range(8, 28):
        msg = policy_msg(x_ref, version=version)
        kind = version % 5
        if kind == 0:
            msg.log_std = [700.0]
        elif kind == 1:
            msg.stiffness = (1e300 * np.eye(3)).reshape(-1).tolist()
        elif kind == 2:
            msg.x_ref = [1e3, 0.0, 0.0]
        elif kind == 3:
            msg.weights = (np.asarray(msg.weights) * 1e6).tolist()
        else:
            msg.version = 1  # backwards
        out.append(msg)
    return out


def _flood(probe: Probe, pub: object, messages: list, period: float) -> float:
    """Publish ``messages`` about one per ``period`` s while another thread spins the probe (so it
    takes every command as it comes); returns the rate."""
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            probe.executor.spin_once(timeout_sec=0.01)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    t0 = time.monotonic()
    try:
        for k, msg in enumerate(messages):
            pub.publish(msg)
            wait = t0 + (k + 1) * period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
    finally:
        rate = len(messages) / (time.monotonic() - t0)
        stop.set()
        spinner.join(timeout=5.0)
    return rate


class _View:
    """(time, values of one node) over a list of (time, (sim values, controller values))."""

    def __init__(self, items: list, which: int) -> None:
        self.items, self.which = items, which

    def __iter__(self):
        return ((t, v[self.which]) for t, v in list(self.items))


def _sim_clock(diags: _View) -> tuple[float, float] | None:
    """(wall time, simulated time) of the sim's latest diagnostics."""
    last = [(t, v) for t, v in diags if v]
    return (last[-1][0], float(last[-1][1]["sim_time"])) if last else None


@pytest.mark.timing  # judges the realtime sim's real-time factor: run with nothing beside
def test_flood_of_bad_messages_keeps_every_command_safe_and_every_fault_clearable(tmp_path: Path):
    domain = allocate_domain_id()
    probe = Probe(domain)
    statuses = probe.collect(ControllerStatus, "/controller_status")
    tasks = probe.collect(TaskStatus, "/task_status", RELIABLE, lambda m: np.array(m.part_position))
    diags = probe.collect(DiagnosticArray, "/diagnostics", RELIABLE,
                          lambda m: (diag_values(m, "sim_bridge"), diag_values(m, "nf_controller")))
    sim_diags = _View(diags, 0)
    ctl_diags = _View(diags, 1)
    rng = np.random.default_rng(0)
    sim = RosProcess([*SIM, "-p", "mode:=realtime", "-p", "command_timeout:=0.5"], domain, tmp_path / "sim.log")
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "idle_mode:=policy",
                      "-p", "max_consecutive_misses:=0"], domain, tmp_path / "controller.log")
    # every command, in order, from a process of its own (a Python probe spinning beside a flood
    # publisher drops some): the bag recorder, read back afterwards
    bag = tmp_path / "bag"
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(bag), "--topics", "/effort_controller/commands",
                      "--depth", "5000"], domain, tmp_path / "recorder.log")
    logs = lambda: f"sim:\n{sim.log()[-3000:]}\ncontroller:\n{ctl.log()[-3000:]}"  # noqa: E731
    try:
        assert probe.spin_until(lambda: "recording /effort_controller/commands (" in rec.log(), 60.0), rec.log()
        assert probe.spin_until(lambda: len(tasks) > 0, 30.0), logs()
        policy_pub = probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
        x_ref = tasks[-1][1]
        policy_pub.publish(policy_msg(x_ref))
        assert probe.spin_until(lambda: any(s.policy_version == 7 and s.mode == ControllerStatus.MODE_IDLE
                                            for _, s in statuses), 60.0), logs()
        probe.spin_for(1.1)
        quiet = _sim_clock(sim_diags)
        probe.spin_for(3.0)  # the same machine without the flood: the baseline
        before = _sim_clock(sim_diags)
        assert quiet and before and before[0] > quiet[0], logs()
        real_time_quiet = (before[1] - quiet[1]) / (before[0] - quiet[0])

        # 1. bad commands to the sim, one per ms: it must keep real time
        cmd_pub = probe.node.create_publisher(Float64MultiArray, "/effort_controller/commands", ALL)
        rate_cmd = _flood(probe, cmd_pub, _bad_commands(3000), 0.001)
        probe.spin_for(1.2)
        after = _sim_clock(sim_diags)
        assert before and after and after[0] > before[0], logs()
        real_time = (after[1] - before[1]) / (after[0] - before[0])

        # 2. bad policies: all refused, version 7 stays
        bad_policies = _bad_policies(x_ref)
        for msg in bad_policies:
            policy_pub.publish(msg)
            probe.spin_for(0.05)
        probe.spin_for(1.0)
        assert statuses[-1][1].policy_version == 7 and statuses[-1][1].mode == ControllerStatus.MODE_IDLE, logs()

        # 3. bad joint states to the controller, one per ms: it holds, and the fault clears
        state_pub = probe.node.create_publisher(JointState, "/joint_states", ALL)
        rate_state = _flood(probe, state_pub, _bad_states(3000, rng), 0.001)
        probe.spin_for(1.5)
        assert statuses[-1][1].mode == ControllerStatus.MODE_SAFE_HOLD, "a bad state latches the hold"
        fault = statuses[-1][1].fault
        assert 0 < len(fault) <= 300, f"fault text bounded: {len(fault)} characters"
        client = probe.node.create_client(Trigger, "/nf_controller/clear_fault")
        assert client.wait_for_service(timeout_sec=10.0)
        cleared = client.call_async(Trigger.Request())
        assert probe.spin_until(cleared.done, 10.0) and cleared.result().success
        n = len(statuses)
        assert probe.spin_until(lambda: len(statuses) > n + 10, 5.0)
        assert all(s.mode == ControllerStatus.MODE_IDLE and not s.fault for _, s in statuses[n + 2:]), \
            [(s.mode, s.fault) for _, s in statuses[n:]][-3:]
        probe.spin_for(1.2)
        assert sim.alive() and ctl.alive(), logs()
    finally:
        ctl.stop()
        sim.stop()
        rec.stop()
        probe.close()
    assert sim.proc.returncode == 0 and ctl.proc.returncode == 0, logs()
    assert "Traceback" not in sim.log() + ctl.log(), logs()
    commands = [np.asarray(m.msg.data, dtype=np.float64) for m in reader.read_messages(bag)]
    taus = np.array([c for c in commands if c.shape == (7,)])
    # the flood's own commands share the topic, every one of them non-finite or of the wrong size:
    # the controller's are the finite 7-value ones, and none of its own may be anything else
    ours = taus[np.all(np.isfinite(taus), axis=1)]
    assert len(ours) > 2000 and len(taus) - len(ours) == 2000, (len(ours), len(taus))
    assert np.all(np.abs(ours) <= TORQUE_LIMITS + 1e-9), "torque limits"
    real_steps = np.abs(np.diff(ours, axis=0)).max(axis=1)
    assert real_steps.max() <= MAX_STEP + 1e-9, f"rate limit: largest step {real_steps.max():.3f} Nm"
    ctl_last = [v for _, v in ctl_diags if v][-1]
    assert int(ctl_last["bad_inputs"]) >= 2900 and int(ctl_last["policy_rejections"]) == len(bad_policies)
    sim_last = [v for _, v in sim_diags if v][-1]
    assert int(sim_last["bad_commands"]) >= 2000
    print(f"flood: {rate_cmd:.0f} bad commands/s, {rate_state:.0f} bad states/s, {len(bad_policies)} bad "
          f"policies; realtime sim at {real_time:.2f}x real time under the command flood ({real_time_quiet:.2f}x "
          f"without it, load {os.getloadavg()[0]:.1f}); {len(ours)} "
          f"controller commands all finite, limited, largest step {real_steps.max():.3f} Nm; fault cleared")
    assert real_time >= 0.9 * real_time_quiet, \
        f"the realtime sim fell to {real_time:.2f}x real time under the flood ({real_time_quiet:.2f}x without)"
