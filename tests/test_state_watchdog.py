"""The controller's stale-state watchdog on, as a driver has it: nf_controller standalone with the
parameters of ``nf_bringup/launch/controller_hardware.launch.py`` (its task file, ``state_timeout``
20 ms, gravity left to the driver, no simulator reset, the safe hold between episodes) against a
hardware-like driver (``tests/peers/hw_driver.py``, franka_ros2's effort convention) whose state
stream stops mid-episode while the arm runs on under the last command it got. The other integration
tests run without it (``state_timeout`` 0, or 2 s where a loaded machine could stall a process)."""

from __future__ import annotations

import ast
import json
import signal
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.action import ActionClient
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import JointMap
from nf_core import panda_spec, qos
from nf_core.topics import POLICY_PARAMETERS

from ros_testing import REPO, RosProcess, allocate_domain_id
from test_nodes import RELIABLE, Probe, diag_values, policy_msg

# a 20 ms timeout between 1 kHz processes, judged by the wall clock: make test runs it alone
pytestmark = [pytest.mark.ros, pytest.mark.timing]

LAUNCH = REPO / "nf_bringup" / "launch" / "controller_hardware.launch.py"
TASK_FILE = REPO / "config" / "gear.yaml"  # the launch file's default ``config``
STATES_OFF = 1.0  # s of wall time the driver sends no state
MAX_STEP = panda_spec.TORQUE_RATE_LIMIT * 1e-3  # Nm, the rate limit's largest step per command


def hardware_parameters() -> dict[str, object]:
    """The parameters ``controller_hardware.launch.py`` gives nf_controller (its one dict literal)."""
    found = [node for node in ast.walk(ast.parse(LAUNCH.read_text())) if isinstance(node, ast.Dict)
             and any(isinstance(k, ast.Constant) and k.value == "state_timeout" for k in node.keys)]
    assert len(found) == 1, f"{LAUNCH.name}: expected one parameter dict with state_timeout, found {len(found)}"
    return ast.literal_eval(found[0])


def ros_value(value: object) -> str:
    """``value`` as a ``-p name:=value`` argument writes it."""
    if isinstance(value, bool):
        return str(value).lower()
    return "''" if value == "" else str(value)


def state_switches(log: str) -> list[dict]:
    """The driver's lines about its state stream (``hw_driver.py``: off / on, q, dq, command)."""
    return [json.loads(line) for line in log.splitlines() if line.startswith('{"joint_states"')]


def test_the_watchdog_holds_the_arm_when_the_drivers_states_stop_mid_episode(tmp_path):
    """Mid-episode the driver's joint_states stop (the arm runs on, under the last command it got):
    within the timeout the watchdog latches the safe hold and commands it without a state. With the
    launch's settings (gravity left to the driver, no hold spring, no velocity to damp) that is zero
    torque, reached within the torque rate limit: the driver applies 0 Nm on top of gravity and the
    arm coasts. Status, /diagnostics (mode, fault, faults) and the episode's result (aborted, with the
    reason once states come back) say so, and the hold stays latched."""
    params = hardware_parameters()
    timeout = float(params["state_timeout"])
    assert timeout > 0.0, f"{LAUNCH.name} turns the watchdog off"
    domain = allocate_domain_id()
    probe = Probe(domain)
    joints = JointMap(panda_spec.JOINT_NAMES)
    arm = ArmModel()
    states = probe.collect(JointState, "joint_states", RELIABLE,
                           convert=lambda m: joints.map(m.name, m.position, m.velocity))
    statuses = probe.collect(ControllerStatus, "controller_status", RELIABLE)
    diags = probe.collect(DiagnosticArray, "/diagnostics", RELIABLE, lambda m: diag_values(m, "nf_controller"))
    # (label, torque): the watchdog's commands answer no state (empty label)
    commands = probe.collect(Float64MultiArray, "effort_controller/commands", RELIABLE,
                             lambda m: (m.layout.dim[0].label if m.layout.dim else "?", np.array(m.data)))
    client = ActionClient(probe.node, RunEpisode, "run_episode")  # before the server: see test_learning_over_ros
    driver = RosProcess([str(REPO / "tests" / "peers" / "hw_driver.py"), "--effort", "measured"], domain,
                        tmp_path / "driver.log")
    args = ["-m", "nf_controller_node.node", "--ros-args", "--params-file", str(TASK_FILE)]
    for name, value in params.items():
        args += ["-p", f"{name}:={ros_value(value)}"]
    ctl = RosProcess(args, domain, tmp_path / "controller.log")
    try:
        logs = lambda: f"driver:\n{driver.log()}\ncontroller:\n{ctl.log()}"  # noqa: E731
        assert probe.spin_until(lambda: len(states) > 100, 30), logs()
        x0 = arm.tcp_position(states[-1][1][0])
        pub = probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
        pub.publish(policy_msg(x0 + np.array([0.08, 0.0, -0.08]), version=3, stiffness=400.0, damping=40.0))
        assert probe.spin_until(lambda: statuses and statuses[-1][1].policy_version == 3, 60), logs()
        assert client.wait_for_server(timeout_sec=10)
        sent = client.send_goal_async(RunEpisode.Goal(policy_version=3, seed=-1, noise_seed=0, duration=5.0,
                                                      deterministic=True))
        assert probe.spin_until(sent.done, 10) and sent.result().accepted, logs()
        result = sent.result().get_result_async()

        def on_its_way() -> bool:  # the episode runs and the arm has moved 1 cm of its 11 cm
            return (statuses[-1][1].mode == ControllerStatus.MODE_RUNNING
                    and np.linalg.norm(arm.tcp_position(states[-1][1][0]) - x0) > 0.01)

        assert probe.spin_until(on_its_way, 20), logs()
        assert statuses[-1][1].fault == "", f"a fault before the states stopped: inconclusive\n{logs()}"
        driver.proc.send_signal(signal.SIGUSR1)  # its state stream stops (by PID)
        stopped = time.monotonic()

        def held() -> bool:
            return any(t > stopped and s.mode == ControllerStatus.MODE_SAFE_HOLD for t, s in statuses)

        assert probe.spin_until(held, 5), logs()
        t_hold, hold = next((t, s) for t, s in statuses if t > stopped and s.mode == ControllerStatus.MODE_SAFE_HOLD)
        probe.spin_for(STATES_OFF - (time.monotonic() - stopped))
        driver.proc.send_signal(signal.SIGUSR1)  # the states come back
        assert probe.spin_until(result.done, 30), logs()
        outcome = result.result().result
        back = time.monotonic()
        # the controller's report after the states came back (diagnostics: every 1 s)
        assert probe.spin_until(lambda: any(t > back + 0.1 and v for t, v in diags), 5), logs()
        report = [v for t, v in diags if t > back + 0.1 and v][-1]
        log = ctl.log()
        switches = state_switches(driver.log())
    finally:
        ctl.stop()
        driver.stop()
        probe.close()
    assert hold.fault.startswith("joint state stale") and f"timeout {timeout * 1e3:.1f} ms" in hold.fault, hold.fault
    assert t_hold - stopped < 0.5, f"safe hold reported {t_hold - stopped:.3f} s after the states stopped"
    assert [s["joint_states"] for s in switches] == ["off", "on"], switches
    off, on = ({k: np.array(v) for k, v in s.items() if k != "joint_states"} for s in switches)
    # mid-motion: the arm moves under a command of the policy's when its states stop
    assert np.abs(off["dq"]).max() > 0.05 and np.abs(off["command"]).max() > 0.5, off
    # the watchdog's commands, sent without a state: they reach zero torque (within the rate limit)
    watchdog = [tau for label, tau in (c for t, c in commands if t > stopped) if label == ""]
    assert len(watchdog) > 10 and np.all(watchdog[-1] == 0.0), watchdog[-1:]
    # What the arm got: zero torque on top of gravity, after the timeout and the ramp down. The watchdog
    # steps by the rate limit's per-command step (1 Nm) every timeout / 4, so its ramp takes
    # |command| / 1 Nm of its periods; bounded with two periods and 100 ms of scheduling to spare.
    zero_after = on["zero_after"]
    steps = int(np.ceil(np.abs(off["command"]).max() / MAX_STEP))
    bound = timeout + (steps + 2) * timeout / 4.0 + 0.1
    assert zero_after is not None and zero_after <= bound, f"zero torque after {zero_after} s (bound {bound:.3f} s)"
    assert np.all(on["command"] == 0.0), on["command"]
    energy_off, energy_on = arm.kinetic_energy(off["q"], off["dq"]), arm.kinetic_energy(on["q"], on["dq"])
    assert not outcome.completed and "joint state stale" in outcome.message, outcome.message
    assert report["mode"] == "safe_hold" and report["faults"] == "1", report
    assert report["fault"].startswith("joint state stale"), report["fault"]
    assert "safe hold: joint state stale" in log, log
    print(f"\nwatchdog: {hold.fault!r}, reported {1e3 * (t_hold - stopped):.0f} ms after the states stopped; "
          f"{len(watchdog)} commands without a state; the driver applied zero torque {1e3 * zero_after:.0f} ms "
          f"after its last state (from {np.abs(off['command']).max():.1f} Nm; bound {1e3 * bound:.0f} ms); arm's "
          f"kinetic energy {energy_off:.3f} J -> {energy_on:.3f} J in {STATES_OFF:.1f} s of coasting; episode: "
          f"{outcome.message!r}")
