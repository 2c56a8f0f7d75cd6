"""franka_driver node: a Franka arm (FR3 or Panda) through libfranka's 1 kHz torque loop, hosting
the flow controller in the same process.

The node connects to the robot (``robot_ip``; ``realtime`` enforce | ignore; ``rt_priority``, the
torque loop thread's SCHED_FIFO priority, and libfranka's own raise of its caller's given back:
``nf_core.thread_priority``), identifies the arm
against the robot's own dynamics model (``franka_driver.robot_model``), builds the controller's
Pinocchio model of that arm, and runs ``franka_driver.loop.FrankaDriverLoop`` (an
``nf_core.driver_loop.DriverLoop``) on its driver thread: per tick readOnce -> controller ->
writeOnce. It is always composed with an ``nf_controller`` node (``nf_franka_stack`` in
``nf_bringup``), which serves the RunEpisode action, rollouts, status, policy and
clear_fault unchanged; this node adds:

- ``joint_states`` (names as the connected robot's description: ``fr3_joint1..7`` or
  ``panda_joint1..7``; effort = the commanded torque, without the robot's gravity) at
  ``joint_state_rate`` from a timer, never from the tick;
- ``/diagnostics`` (``franka_driver: robot``): loop timing (read -> write latency, late ticks,
  missed cycles), libfranka exceptions and the latest error text, reset outcomes, TCP, depth;
- ``~/recover`` (std_srvs/Trigger): after a libfranka error (a reflex), a person who has made the
  cell safe restarts torque control (the controller then still holds until its clear_fault);
- reset *motions* before episodes and success from kinematics (fixture parameters).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from nf_core import qos, topics
from nf_core.driver_loop import loop_priority
from nf_core.ros_runtime import declare_read_only
from nf_core.serialized_message import SerializedMessage
from nf_core.task_spec import HELD_PART_HELP, held_part_inertia
from nf_core.thread_priority import AUTO, open_robot
from nf_core.tick_timing import latency_summary

from .loop import DriverConfig, FrankaDriverLoop
from .robot_model import ROBOT_KINDS, Identification, WrongRobotModelError, identify

_D = DriverConfig()
PARAMETERS = {
    "robot_ip": ("172.16.0.2", "address of the robot's FCI (franky-sim: 127.0.0.1)"),
    "realtime": ("enforce", "enforce (needs a realtime kernel, as on the robot's PC) | ignore (other kernels, sim)"),
    "rt_priority": (AUTO, "SCHED_FIFO priority of the torque loop's thread (only): -1 auto (99, as libfranka "
                          "gives its threads; with realtime ignore only if allowed), 0 normal, 1..99"),
    "robot_model": ("auto", f"arm type, checked against the robot's own model: {' | '.join(ROBOT_KINDS)}"),
    "held_part": ("gear", f"part in the hand (must equal nf_controller's): {HELD_PART_HELP}"),
    "start_position": (_D.start_position.tolist(), "m, TCP position the reset motion drives to before each episode"),
    "fixture_position": (_D.fixture_position.tolist(),
                         "m, the fixture's mouth (insertion axis along -z) in the base frame"),
    "goal": ([0.0], "m, x_ref an episode's policy must have: the fixture's goal ([0.0] or empty: not checked)"),
    "goal_tolerance": (0.001, "m, largest difference between the policy's x_ref and goal"),
    "fixture_radius": (_D.fixture_radius, "m, lateral distance from the fixture axis that counts as inside"),
    "success_depth": (_D.success_depth, "m below the fixture mouth that counts as success"),
    "reset_timeout": (_D.reset_timeout, "s of robot time the reset motion may take"),
    "reset_tolerance": (_D.reset_tolerance, "m from start_position that counts as arrived"),
    "reset_speed": (_D.reset_speed, "m/s, TCP speed below which the arm counts as still"),
    "reset_settle": (_D.reset_settle, "ticks in a row arrived and still before the episode starts"),
    "reset_stiffness": (_D.reset_stiffness, "N/m, the reset motion's spring (identity flow)"),
    "reset_damping": (_D.reset_damping, "N s/m, the reset motion's damping"),
    "reset_force_bound": (_D.reset_force_bound, "N, bound on the reset motion's pull, whatever the policy's law "
                                                "(0: none)"),
    "reset_posture_stiffness": (_D.reset_posture_stiffness,
                                "Nm/rad, the reset motion's joint spring to reset_posture (0: none)"),
    "reset_posture_damping": (_D.reset_posture_damping, "Nm s/rad, the reset motion's joint damping with it"),
    "reset_posture": ([0.0], "rad, the joints the reset motion returns to ([0.0] or empty: where the first "
                             "reset reached start_position)"),
    "reset_via": ([0.0], "m, TCP points (x y z, ...) a reset motion passes through before start_position, e.g. "
                         "over a clamp ([0.0] or empty: straight to the start)"),
    "reset_via_tolerance": (_D.reset_via_tolerance, "m from a reset_via point that counts as passed"),
    "automatic_error_recovery": (False, "after a libfranka error: recover and go on without a person"),
    "recovery_wait": (_D.recovery_wait, "s before an automatic recovery"),
    "gravity_headroom": (True, "clamp each command to limit - |g(q)| (the robot adds g(q) on top)"),
    "joint_state_rate": (100.0, "joint_states messages per s (from a timer, not the tick)"),
    "diagnostics_period": (1.0, "s between /diagnostics messages"),
    "guide": (False, "hand-guiding: every episode, after its reset motion, commands zero torque (the robot's "
                     "gravity compensation only) so a person moves the arm; docs/hardware.md"),
    "guide_joint_speed": (_D.guide_joint_speed, "rad/s: a joint faster than this stops hand-guiding into the hold"),
    "guide_limit_margin": (_D.guide_limit_margin, "rad: a joint this close to a limit stops hand-guiding"),
    "guide_timeout": (_D.guide_timeout, "s of robot time a guided episode may last"),
    "timing_log": ("", "file (.npy) for every read->write latency, periods and a .json summary at shutdown"),
}


def _check(p: dict) -> None:
    if p["realtime"] not in ("enforce", "ignore"):
        raise ValueError(f"realtime must be enforce or ignore, got {p['realtime']!r}")
    if p["robot_model"] not in ROBOT_KINDS:
        raise ValueError(f"robot_model must be one of {ROBOT_KINDS}, got {p['robot_model']!r}")
    held_part_inertia(p["held_part"])
    for name in ("joint_state_rate", "diagnostics_period"):
        if not p[name] > 0.0:
            raise ValueError(f"{name} must be > 0, got {p[name]}")


def via_points(values: list[float]) -> np.ndarray | None:
    """``reset_via``'s flat list as (k, 3) points (None for [0.0] or empty); ValueError for another length."""
    if len(values) <= 1:
        return None
    if len(values) % 3:
        raise ValueError(f"reset_via must be x y z per point (a multiple of 3 values), got {len(values)}: {values}")
    return np.asarray(values, float).reshape(-1, 3)


def driver_config(p: dict, keep_timing: bool = False) -> DriverConfig:
    """The loop's settings from the node's parameters (checked)."""
    config = DriverConfig(
        start_position=np.asarray(p["start_position"], float),
        fixture_position=np.asarray(p["fixture_position"], float),
        fixture_radius=p["fixture_radius"], success_depth=p["success_depth"], reset_timeout=p["reset_timeout"],
        reset_tolerance=p["reset_tolerance"], reset_speed=p["reset_speed"], reset_settle=p["reset_settle"],
        reset_stiffness=p["reset_stiffness"], reset_damping=p["reset_damping"],
        reset_force_bound=p["reset_force_bound"],
        reset_posture_stiffness=p["reset_posture_stiffness"], reset_posture_damping=p["reset_posture_damping"],
        reset_posture=np.asarray(p["reset_posture"], float) if len(p["reset_posture"]) > 1 else None,
        reset_via=via_points(p["reset_via"]), reset_via_tolerance=p["reset_via_tolerance"],
        automatic_error_recovery=p["automatic_error_recovery"], recovery_wait=p["recovery_wait"],
        gravity_headroom=p["gravity_headroom"], keep_timing=keep_timing, guide=p["guide"],
        guide_joint_speed=p["guide_joint_speed"], guide_limit_margin=p["guide_limit_margin"],
        guide_timeout=p["guide_timeout"],
        goal=np.asarray(p["goal"], float) if len(p["goal"]) == 3 else None, goal_tolerance=p["goal_tolerance"])
    config.check()
    return config


class FrankaDriverNode(Node):
    """Connects to the robot and identifies it; ``attach(controller)`` builds the loop around the
    composed controller's host; ``start_driver()`` starts the torque loop. See the module docstring."""

    def __init__(self) -> None:
        super().__init__("franka_driver")
        p = declare_read_only(self, PARAMETERS)
        _check(p)
        self.params = p
        self.config = driver_config(p, keep_timing=bool(p["timing_log"]))
        # the loop thread's realtime priority: checked now, before any connection, never dropped silently
        self.rt_priority = loop_priority(p["rt_priority"], p["realtime"] == "enforce", "the torque loop")
        import pylibfranka as franka  # here, so that --help and parameter errors need no robot

        self.franka = franka
        self.exceptions = (franka.FrankaException, franka.ControlException, franka.CommandException,
                           franka.NetworkException, franka.RealtimeException, franka.InvalidOperationException)
        mode = franka.RealtimeConfig.kEnforce if p["realtime"] == "enforce" else franka.RealtimeConfig.kIgnore
        self._realtime_mode = mode
        try:
            self.robot = self._connect()
            state = self.robot.read_once()
            model = self.robot.load_model()
        except self.exceptions as exc:
            raise ValueError(f"cannot connect to the robot at {p['robot_ip']} (realtime {p['realtime']}): "
                             f"{type(exc).__name__}: {exc}") from None
        try:
            self.identification: Identification = identify(p["robot_model"], state, model)
        except WrongRobotModelError as exc:
            raise ValueError(str(exc)) from None
        self.spec = self.identification.spec
        self.part = held_part_inertia(p["held_part"])
        self.arm = self.spec.arm_model(self.part)  # the controller's model (its tick thread owns it)
        self._tcp_arm = self.spec.arm_model(self.part)  # the driver's own copy for the TCP position
        self.joint_names = list(self.spec.joint_names)
        self.get_logger().info(f"connected to {p['robot_ip']}: {self.identification.summary()}; joints "
                               f"{self.joint_names}; robot mode {state.robot_mode}")
        self.driver: FrankaDriverLoop | None = None
        self._latest: tuple[Any, ...] | None = None  # (q, dq, tau copy, stamp_ns) of the last tick
        n = len(self.joint_names)
        msg = JointState(name=list(self.joint_names), position=[0.0] * n, velocity=[0.0] * n, effort=[0.0] * n)
        # serialized once and rewritten in place: less GIL time on the executor per message
        self._state_raw = SerializedMessage(msg, floats=("position", "velocity", "effort"), stamp="header.stamp")
        self._state_pub = self.create_publisher(JointState, topics.JOINT_STATES, qos.PUBLISH)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos.DIAGNOSTICS)
        self.create_service(Trigger, "~/recover", self._on_recover)
        self.create_timer(1.0 / p["joint_state_rate"], self._publish_state)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self._logged_error = ""

    def _connect(self) -> Any:
        """A new libfranka connection to ``robot_ip``."""
        # libfranka's constructor would leave this thread (the executor, or the loop after a network
        # error) at SCHED_FIFO 99: open_robot gives it its own scheduling back
        return open_robot(lambda: self.franka.Robot(self.params["robot_ip"], self._realtime_mode))

    # ------------------------------------------------------------------ composition
    def attach(self, controller: Any) -> FrankaDriverLoop:
        """Build the torque loop around a composed ``NFControllerNode``; refuse settings that are
        unsafe on a Franka, apply this arm's joint limits, and log the effective safety values."""
        cp = controller.params
        if cp["gravity_compensation"]:
            raise ValueError("nf_controller's gravity_compensation is true, but a Franka compensates gravity "
                             "itself (it would be applied twice): use --params-file config/franka.yaml, "
                             "or -p nf_controller:gravity_compensation:=false")
        if cp["held_part"] != self.params["held_part"]:
            raise ValueError(f"held_part differs: nf_controller {cp['held_part']!r}, franka_driver "
                             f"{self.params['held_part']!r} (set both, e.g. in the /** section)")
        loop = controller.loop
        if tuple(loop.joints.joint_names) != tuple(self.joint_names):
            raise ValueError(f"controller joints {list(loop.joints.joint_names)} differ from the robot's "
                             f"{self.joint_names}")
        spec = self.spec
        spec.fit_loop(loop)  # the connected arm's ranges and limits (the loop's defaults are the Panda's)
        law = loop.controller.law
        tcp = self._tcp_arm.tcp_position
        self.driver = FrankaDriverLoop(self.robot, controller.host, tcp, self.config, self.franka.Torques,
                                       self.exceptions, after_tick=self._after_tick, connect=self._connect,
                                       rt_priority=self.rt_priority)
        self.robot = None  # the loop owns the connection (and replaces it after a network error)
        self.get_logger().warn(
            "EFFECTIVE SAFETY VALUES: "
            f"arm {spec.kind}, gravity_compensation {cp['gravity_compensation']} (robot adds g(q)), "
            f"torque limits {law.torque_limits.tolist()} Nm minus |g(q)| + 0.5 Nm "
            f"({'on' if self.config.gravity_headroom else 'OFF'}), rate limit {law.torque_rate_limit:g} Nm/s, "
            f"hold_damping {law.hold_damping:g} Nm s/rad, hold_stiffness {law.hold_stiffness:g} Nm/rad, "
            "joint_damping, k_rot, d_rot and the force bound: the policy's (logged when it is installed), "
            f"joint-limit springs {law.joint_limit_stiffness:g} Nm/rad within "
            f"{law.joint_limit_margin:g} rad of the limits, idle_mode {loop.config.idle_mode}, "
            f"deadline {loop.config.deadline * 1e3:g} ms x "
            f"{loop.config.max_consecutive_misses}, joint ranges {np.round(loop.q_min, 3).tolist()} .. "
            f"{np.round(loop.q_max, 3).tolist()} rad, reset {self.config.reset_stiffness:g} N/m / "
            f"{self.config.reset_damping:g} N s/m (pull at most {self.config.reset_force_bound:g} N) to "
            f"{self.config.start_position.tolist()}"
            f"{'' if self.config.reset_via is None else ' via ' + str(self.config.reset_via.tolist())}, posture spring "
            f"{self.config.reset_posture_stiffness:g} Nm/rad / {self.config.reset_posture_damping:g} Nm s/rad to "
            f"{'the first reset' if self.config.reset_posture is None else self.config.reset_posture.tolist()}, within "
            f"{self.config.reset_timeout:g} s, fixture {self.config.fixture_position.tolist()}, goal "
            f"{'any' if self.config.goal is None else self.config.goal.tolist()}, "
            f"automatic_error_recovery {self.config.automatic_error_recovery}"
            + (f"; HAND-GUIDING: episodes command zero torque, stopped into the hold above "
               f"{self.config.guide_joint_speed:g} rad/s, within {self.config.guide_limit_margin:g} rad of a limit "
               f"or after {self.config.guide_timeout:g} s" if self.config.guide else ""))
        return self.driver

    def start_driver(self) -> None:
        """Start the torque loop on its own thread."""
        if self.driver is not None:
            self.driver.start(self.get_logger())

    def stop_driver(self) -> None:
        """Stop the torque loop (ends the motion with a zero command) and join its thread."""
        if self.driver is not None:
            self.driver.stop()

    def _after_tick(self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray, stamp_ns: int) -> None:
        self._latest = (q, dq, tau.copy(), stamp_ns)  # one tuple: read whole by the publisher

    # ------------------------------------------------------------------ publishing
    def _publish_state(self) -> None:
        latest = self._latest
        if latest is None:
            return
        q, dq, tau, stamp_ns = latest
        raw = self._state_raw
        raw.set_stamp(stamp_ns)
        raw.floats["position"][:] = q
        raw.floats["velocity"][:] = dq
        raw.floats["effort"][:] = tau
        self._state_pub.publish(raw.payload())

    def _publish_diagnostics(self) -> None:
        d = self.driver
        if d is None:
            return
        status = DiagnosticStatus(name="franka_driver: robot",
                                  hardware_id=f"{self.spec.kind}@{self.params['robot_ip']}")
        if d.in_error:
            status.level, status.message = DiagnosticStatus.ERROR, f"libfranka error: {d.last_error}"
        elif d.sessions:
            status.level, status.message = DiagnosticStatus.OK, "torque control" + (", hand-guiding" if d.config.guide
                                                                                      else "")
        else:
            status.level, status.message = DiagnosticStatus.OK, "starting"
        if d.last_error and d.last_error != self._logged_error:
            self._logged_error = d.last_error
            self.get_logger().error(f"libfranka: {d.last_error}")
        lat = latency_summary(d.timing.take_window())
        values = {"arm": self.spec.kind, "exceptions": d.exceptions, "last_error": d.last_error,
                  "in_error": d.in_error, "recoveries": d.recoveries, "sessions": d.sessions,
                  "loop_scheduling": d.scheduling,
                  **{f"latency_{k}": f"{v:.1f}" for k, v in lat.items()}, **d.timing.counters(),
                  "resets_done": d.resets_done, "resets_failed": d.resets_failed, "last_reset": d.last_reset,
                  "guides": d.guides, "guide_stops": d.guide_stops, "last_guide_stop": d.last_guide_stop,
                  "tcp": np.round(d.x, 4).tolist(), "insertion_depth": f"{d.depth:.4f}", "success": d.success}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)

    def _on_recover(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        d = self.driver
        if d is None or not d.in_error:
            response.success, response.message = False, "no libfranka error to recover from"
            return response
        d.request_recovery()
        response.success = True
        response.message = (f"recovering from: {d.last_error}; the controller holds until "
                            "nf_controller/clear_fault")
        self.get_logger().warn(response.message)
        return response

    # ------------------------------------------------------------------ shutdown
    def write_timing_log(self, path: Path) -> None:
        """Every read->write latency (s) to ``path`` (.npy), periods to ``<path>.periods.npy``, summary .json."""
        t = self.driver.timing
        lat = np.frombuffer(t.latency, dtype=np.float64).copy()
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, lat)
        np.save(path.with_suffix(".periods.npy"), np.frombuffer(t.periods, dtype=np.float64).copy())
        summary = {"latency": latency_summary(t.latency), "period": latency_summary(t.periods), **t.counters(),
                   "exceptions": self.driver.exceptions, "last_error": self.driver.last_error}
        path.with_suffix(".json").write_text(json.dumps(summary, indent=1))
        self.get_logger().info(f"timing log: {lat.size} latencies to {path}")

    def destroy_node(self) -> None:
        """Stop the torque loop, write the timing log (when asked for), destroy the node."""
        self.stop_driver()
        if self.driver is not None and self.params["timing_log"]:
            self.write_timing_log(Path(self.params["timing_log"]))
        super().destroy_node()

