"""A standalone controller restarted under a running driver ramps from the torque the arm is
applying (the driver's ``effort``), within the torque rate limit from its first command on, under both
effort conventions: the command the driver applies (our simulator's) and the joint torque the arm
measures, gravity included (franka_ros2's, libfranka's tau_J)."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import JointMap
from nf_core import panda_spec, qos
from nf_core.topics import POLICY_PARAMETERS

from ros_testing import REPO, RosProcess, allocate_domain_id
from test_nodes import RELIABLE, Probe, policy_msg

MAX_STEP = panda_spec.TORQUE_RATE_LIMIT * 1e-3  # Nm per 1 ms command
# the probe keeps every command it is sent (a lagging reader with a history of 10 loses some)
EVERY = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE)
CONTROLLER = ["-m", "nf_controller_node.node", "--ros-args", "-p", "gravity_compensation:=false",
              "-p", "reset_service:=''", "-p", "state_timeout:=2.0", "-p", "max_consecutive_misses:=500"]


@pytest.mark.parametrize("effort", ["command", "measured"])
def test_restarted_controller_starts_from_the_applied_torque(tmp_path, effort):
    domain = allocate_domain_id()
    probe = Probe(domain)
    joints = JointMap(panda_spec.JOINT_NAMES)
    arm = ArmModel()
    # (q, dq, effort, the driver's stamp in s): the probe can lag the 1 kHz stream on two loaded cores,
    # so what the driver applies at a moment is read from a state it stamped after that moment
    states = probe.collect(JointState, "joint_states", RELIABLE,
                           convert=lambda m: (*joints.map(m.name, m.position, m.velocity),
                                              joints.map(m.name, m.effort, m.effort)[0],
                                              m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec))
    commands = probe.collect(Float64MultiArray, "effort_controller/commands", EVERY,
                             convert=lambda m: np.array(m.data))
    watch = probe.node.create_subscription(Float64MultiArray, "effort_controller/commands", lambda m: None, EVERY)
    driver = RosProcess([str(REPO / "tests" / "peers" / "hw_driver.py"), "--effort", effort], domain,
                        tmp_path / "driver.log")
    controller = [*CONTROLLER, "-p", f"driver_effort:={effort}"]
    first = RosProcess([*controller, "-p", "idle_mode:=policy"], domain, tmp_path / "first.log")
    second = None
    try:
        assert probe.spin_until(lambda: len(states) > 100, 30), driver.log()
        x0 = arm.tcp_position(states[-1][1][0])
        pub = probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
        pub.publish(policy_msg(x0 + np.array([0.08, 0.0, -0.08]), version=3, stiffness=400.0, damping=40.0))
        # the first controller pulls the arm towards a goal 11 cm away: wait until it commands several Nm
        assert probe.spin_until(lambda: commands and np.abs(commands[-1][1]).max() > 3.0, 60), first.log()
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait(10)
        killed_wall = time.time()
        # the probe may still hold a backlog of the dead controller's commands (1 kHz, on two loaded
        # cores): only once none has come for 0.5 s is every later command the second controller's
        assert probe.spin_until(lambda: time.monotonic() - commands[-1][0] > 0.5, 30), "commands go on after the kill"
        killed = time.monotonic()
        # what the driver applies now (the dead controller's last command), from a state stamped after the kill
        assert probe.spin_until(lambda: states[-1][1][3] > killed_wall + 0.1, 30), "no joint state after the kill"
        q, _, held = states[-1][1][:3]  # the effort the driver reports for it
        # the command the driver applies on top of gravity (a SIGKILL can cut the dead controller's last
        # sends to the driver short while the probe got them: only the driver's report tells)
        last = held if effort == "command" else held - arm.gravity(q)
        assert np.abs(last).max() > 2.0, f"the driver applies only {last}: nothing to ramp from"
        if effort == "measured":  # the reported torque holds gravity: taken as the command it would step by it
            assert np.abs(held - last).max() > 5.0, f"effort {held} vs command {last}: no gravity in it?"
        # A reader sees only what a writer sends after they matched, and discovery can take seconds on
        # loaded cores: with the driver paused (no states, so no commands) until the probe has matched
        # the new controller's publisher, the probe sees its first command
        driver.proc.send_signal(signal.SIGSTOP)
        matched_before = watch.get_publisher_count()  # the dead controller's may still be counted
        second = RosProcess([*controller, "-p", "idle_mode:=hold"], domain, tmp_path / "second.log")
        try:
            assert probe.spin_until(lambda: watch.get_publisher_count() > matched_before, 60), second.log()
            probe.spin_for(0.2)
        finally:
            driver.proc.send_signal(signal.SIGCONT)
        assert probe.spin_until(lambda: commands and commands[-1][0] > killed + 0.2, 60), second.log()
        assert probe.spin_until(lambda: sum(t > killed for t, _ in commands[-200:]) >= 200, 30), second.log()
        new = [c for t, c in commands if t > killed]  # the second controller's, from its first on
        applied = last  # the driver's command changes only when a command arrives: none came since the kill
        step = np.abs(new[0] - applied)
        assert step.max() <= MAX_STEP + 1e-6, (f"first command {np.round(new[0], 3)} steps {np.round(step, 3)} Nm "
                                               f"from the applied {np.round(applied, 3)}\n{second.log()}")
        steps = np.abs(np.diff(np.array(new), axis=0))
        assert steps.max() <= MAX_STEP + 1e-6, f"a later step of {steps.max():.3f} Nm: commands lost on the way?"
        assert probe.spin_until(lambda: "starts from the applied torque" in second.log(), 10), second.log()
    finally:
        for proc in (second, first, driver):
            if proc is not None:
                proc.stop()
        probe.close()
