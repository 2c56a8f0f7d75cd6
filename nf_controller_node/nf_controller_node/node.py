"""nf_controller node: the stable flow controller between ``joint_states`` and
``effort_controller/commands`` (ros2_control conventions).

Each joint state is answered within its own callback (EventsExecutor) with one torque command:
the flow controller, or the safe hold (gravity compensation + joint damping) on any bad input.
Policy parameters arrive on ``/policy_parameters`` (reliable, transient local), are validated
and swapped in between episodes. ``controller_status`` (50 Hz) and ``/diagnostics`` (1 Hz)
report mode, fault, energy and loop latency. ``~/clear_fault`` re-arms after a fault.
The checks and counters live in ``nf_controller_node.control_loop``.
"""

from __future__ import annotations

import array
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nf_msgs.msg import ControllerStatus
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from .arm_model import ArmModel
from .control_loop import MODE_IDLE, MODE_RUNNING, MODE_SAFE_HOLD, ControlLoop, LoopConfig
from .panda_spec import GEAR_PART
from .policy_params import PolicyParameterError, PolicyParameters
from .ros_runtime import declare_read_only, run_node
from .topics import (
    COMMANDS,
    CONTROLLER_STATUS,
    DIAGNOSTICS,
    JOINT_STATES,
    POLICY_PARAMETERS,
    stamp_label,
)
from .torque_law import TorqueLawConfig

_LAW = TorqueLawConfig()
PARAMETERS = {
    "gravity_compensation": (True, "add g(q) to the torque; false when the driver compensates gravity (Franka)"),
    "held_part": ("gear", "mass model of the part in the hand: gear | none"),
    "k_rot": (_LAW.k_rot, "orientation stiffness about the insertion orientation, Nm/rad"),
    "d_rot": (_LAW.d_rot, "orientation damping, Nm s/rad"),
    "joint_damping": (_LAW.joint_damping, "joint damping for the null space, Nm s/rad"),
    "hold_damping": (_LAW.hold_damping, "joint damping of the safe hold, Nm s/rad"),
    "deadline": (0.001, "s; a step taking longer is a deadline miss"),
    "max_consecutive_misses": (20, "deadline misses in a row that latch the safe hold (0: never)"),
    "state_timeout": (0.0, "s without a joint state before the safe hold (realtime drivers; 0: off)"),
    "status_rate": (50.0, "controller_status messages per s"),
    "diagnostics_period": (1.0, "s between /diagnostics messages"),
}
STATE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
POLICY_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
_MODE_NAMES = {MODE_IDLE: "idle", MODE_RUNNING: "running", MODE_SAFE_HOLD: "safe_hold"}


def _loop_from(p: dict) -> ControlLoop:
    if p["held_part"] not in ("gear", "none"):
        raise ValueError(f"held_part must be 'gear' or 'none', got {p['held_part']!r}")
    for name in ("status_rate", "diagnostics_period"):
        if not p[name] > 0.0:
            raise ValueError(f"{name} must be > 0, got {p[name]}")
    law = TorqueLawConfig(k_rot=p["k_rot"], d_rot=p["d_rot"], joint_damping=p["joint_damping"],
                          hold_damping=p["hold_damping"], gravity_compensation=p["gravity_compensation"])
    config = LoopConfig(deadline=p["deadline"], max_consecutive_misses=p["max_consecutive_misses"],
                        state_timeout=p["state_timeout"])
    arm = ArmModel(part=GEAR_PART if p["held_part"] == "gear" else None)
    return ControlLoop(arm, law, config)


class NFControllerNode(Node):
    """Wires a ``ControlLoop`` to the arm's topics; see the module docstring."""

    def __init__(self, state_qos: QoSProfile = STATE_QOS, policy_qos: QoSProfile = POLICY_QOS) -> None:
        super().__init__("nf_controller")
        p = declare_read_only(self, PARAMETERS)
        self.params = p
        self.loop = _loop_from(p)
        self._dim = MultiArrayDimension(label="", size=7, stride=7)
        self._cmd = Float64MultiArray()
        self._cmd.layout.dim = [self._dim]
        self._cmd_pub = self.create_publisher(Float64MultiArray, COMMANDS, state_qos)
        self._status_pub = self.create_publisher(ControllerStatus, CONTROLLER_STATUS, state_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS, state_qos)
        self.create_subscription(JointState, JOINT_STATES, self._on_joint_state, state_qos)
        self.create_subscription(PolicyParametersMsg, POLICY_PARAMETERS, self._on_policy, policy_qos)
        self.create_service(Trigger, "~/clear_fault", self._on_clear_fault)
        self.create_timer(1.0 / p["status_rate"], self._publish_status)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        if p["state_timeout"] > 0.0:
            self.create_timer(max(p["state_timeout"] / 4.0, 0.001), self._on_watchdog)
        self._stamp = None
        self._tau_norm = 0.0
        self._bad_logged = 0
        self.get_logger().info(
            f"flow controller up: gravity compensation {'on' if p['gravity_compensation'] else 'off (driver)'}, "
            f"joints {list(self.loop.joints.joint_names)}; holding until policy parameters arrive")

    # ------------------------------------------------------------------ the 1 kHz path
    def _on_joint_state(self, msg: JointState) -> None:
        t0 = time.perf_counter()
        stamp = msg.header.stamp
        tau, new_fault = self.loop.on_joint_state(msg.name, msg.position, msg.velocity,
                                                  stamp.sec * 1_000_000_000 + stamp.nanosec, time.monotonic())
        self._dim.label = stamp_label(stamp.sec * 1_000_000_000 + stamp.nanosec)  # lockstep handshake
        self._publish_command(tau)
        self._stamp = stamp
        missed = self.loop.record_latency(time.perf_counter() - t0)
        if new_fault or missed:
            self.get_logger().error(f"safe hold: {new_fault or missed}")
        elif self.loop.bad_inputs != self._bad_logged:
            self.get_logger().error(f"bad joint state rejected ({self.loop.bad_inputs} so far); holding: "
                                    f"{self.loop.fault}", throttle_duration_sec=1.0)
        self._bad_logged = self.loop.bad_inputs

    def _publish_command(self, tau: np.ndarray) -> None:
        self._cmd.data = array.array("d", tau.tobytes())
        self._cmd_pub.publish(self._cmd)
        self._tau_norm = float(np.linalg.norm(tau))

    def _on_watchdog(self) -> None:
        tau, new_fault = self.loop.on_timer(time.monotonic())
        if tau is not None:
            self._dim.label = ""  # answers no state
            self._publish_command(tau)
        if new_fault:
            self.get_logger().error(f"safe hold: {new_fault}")

    # ------------------------------------------------------------------ policy and faults
    def _on_policy(self, msg: PolicyParametersMsg) -> None:
        old = self.loop.policy_version
        try:
            params = PolicyParameters.from_msg(msg)
            now = self.loop.set_policy(params)
        except PolicyParameterError as exc:
            self.loop.policy_rejections += 1
            self.get_logger().error(f"rejected policy parameters version {msg.version}: {exc} "
                                    f"(keeping version {old})")
            return
        a = params.arch
        self.get_logger().info(
            f"policy version {params.version} {'installed' if now else 'queued until the episode ends'}: "
            f"n_flow={a.n_flow}, n_hidden={a.n_hidden}, {a.activation}, x_ref={params.x_ref.tolist()}")

    def _on_clear_fault(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        old = self.loop.clear_fault()
        response.success = True
        response.message = f"cleared: {old}" if old else "no fault latched"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------ reporting
    def _publish_status(self) -> None:
        loop = self.loop
        value, rate = loop.lyapunov()
        msg = ControllerStatus(mode=loop.mode, fault=loop.fault, policy_version=loop.policy_version,
                               lyapunov=value, lyapunov_rate=rate, torque_norm=self._tau_norm,
                               deadline_misses=loop.deadline_misses)
        if self._stamp is not None:
            msg.header.stamp = self._stamp
        msg.header.frame_id = "panda_link0"
        if loop.have_state:
            msg.x = loop.controller.arm.tcp_position(loop.q).tolist()
        if loop.policy is not None:
            msg.x_ref = loop.policy.x_ref.tolist()
        self._status_pub.publish(msg)

    def _publish_diagnostics(self) -> None:
        loop = self.loop
        lat = loop.latency.report()
        status = DiagnosticStatus(name="nf_controller: control loop", hardware_id="panda")
        mode = loop.mode
        if mode == MODE_SAFE_HOLD:
            status.level = DiagnosticStatus.WARN if loop.policy is None else DiagnosticStatus.ERROR
            status.message = f"safe hold: {loop.fault}"
        else:
            status.level, status.message = DiagnosticStatus.OK, _MODE_NAMES[mode]
        values = {
            "mode": _MODE_NAMES.get(mode, str(mode)), "fault": loop.fault, "policy_version": loop.policy_version,
            "steps": loop.steps, "steps_in_window": lat["count"],
            "latency_p50_us": f"{lat['p50_us']:.1f}", "latency_p90_us": f"{lat['p90_us']:.1f}",
            "latency_p99_us": f"{lat['p99_us']:.1f}", "latency_max_us": f"{lat['max_us']:.1f}",
            "deadline_misses": loop.deadline_misses, "faults": loop.faults, "bad_inputs": loop.bad_inputs,
            "policy_rejections": loop.policy_rejections,
        }
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)


def main(args: list[str] | None = None) -> int:
    """Console script ``nf_controller``."""
    return run_node(NFControllerNode, "nf_controller", "Stable normalizing-flow torque controller for the "
                    "Panda (joint_states -> effort_controller/commands).", args)


if __name__ == "__main__":
    raise SystemExit(main())

