"""sim_bridge node: the MuJoCo Panda behind the topics a ros2_control effort driver uses.

Publishes ``joint_states`` (stamp = simulated time), ``clock``, ``task_status`` and
``/diagnostics``; takes ``effort_controller/commands``; serves ``~/reset``. The decisions
(command checks, timeout, safe hold, clock) live in ``sim_bridge_node.bridge``.

Modes (parameter ``mode``):

- ``lockstep``: publish a state, wait for the command that answers it, step once, publish the
  next state. Deterministic, as fast as the loop allows. If no command comes within
  ``lockstep_resend`` s of wall time (e.g. the controller is not up yet, or a message was
  lost) the same state is published again. A bad command is ignored: the simulation waits.
- ``realtime``: a 1 kHz wall-clock timer steps with the last command; after
  ``command_timeout`` s without one the bridge holds the arm (gravity compensation + joint
  damping) and counts a command timeout, as a real arm's driver would. It also times each
  state-to-command round trip and counts deadline misses (``response_timing``); the numbers go
  to ``/diagnostics`` and, with ``response_log`` set, every latency to a file at shutdown.

Composed (``SimBridgeNode(host=...)``, started by ``nf_sim_stack``): the controller runs in this
process and the bridge calls it directly every step on a driver thread
(``sim_bridge_node.composed``); the node still publishes ``joint_states``, ``clock``,
``task_status``, ``/diagnostics`` and, for bags and re-simulation, the applied command on
``effort_controller/commands`` (labelled with the state it answers), and serves ``~/reset``.
Nothing reads those four monitoring topics on the tick's path, so they go out only while they
have a subscriber (looked up every ``LISTENERS_PERIOD``; ``/diagnostics`` counts what was left
out as ``monitor_skipped``): a headless learning run does not pay for them.
In realtime mode the driver thread, and only it, runs at the SCHED_FIFO priority ``rt_priority``
gives (``nf_core.thread_priority``; auto: 99 when the system allows it), as the Franka
driver's torque loop does: both are an ``nf_core.driver_loop.DriverLoop``.

Joint friction: fixed for the node's life (``joint_friction``, ``joint_viscous``), or drawn per
episode from each reset's seed (the task file's shared ``friction_coulomb``, ``friction_viscous``
ranges; ``nf_core.friction``), the same draw the in-process trainer's resets make. Setting both
kinds is refused. Each reset's draw goes to the log and ``/diagnostics`` (``episode_friction_*``).
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nf_msgs.msg import TaskStatus
from nf_msgs.srv import ResetSim
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from nf_core import qos, topics
from nf_core.driver_loop import LoopHost, loop_priority
from nf_core.friction import FrictionRanges
from nf_core.ros_runtime import declare_read_only, run_node
from nf_core.serialized_message import SerializedMessage
from nf_core.task_spec import load_task
from nf_core.thread_priority import AUTO, top_priority
from nf_core.tick_timing import latency_summary
from nf_core.topics import parse_stamp_label
from sim_bridge_node.bridge import ACCEPTED, BridgeConfig, SimBridge
from sim_bridge_node.composed import SimDriverLoop
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.response_timing import ResponseTiming
from sim_bridge_node.scenes import TASKS

PARAMETERS = {
    "task": ("gear", f"scene: one of {TASKS} or the path of a task file (config/tasks/README.md)"),
    "block_plane": ("vertical", "block task only: vertical | horizontal"),
    "mode": ("lockstep", "lockstep (step per command, publishes clock) | realtime (1 kHz wall clock)"),
    "driver_gravity_compensation": (False, "add the simulator's gravity torque to every command (like Franka)"),
    "command_timeout": (0.05, "realtime: s without a command before the safe hold"),
    "hold_damping": (2.0, "joint damping of the safe hold, Nm s/rad"),
    "hold_stiffness": (0.0, "joint spring of the safe hold to where it began, Nm/rad (0: damping only)"),
    "joint_friction": (0.0, "Coulomb joint friction, Nm (MuJoCo frictionloss): one value for every joint or a list "
                            "of one per joint; 0: none (the default)"),
    "joint_viscous": (0.0, "viscous joint friction added to the arm's own damping (panda_spec.JOINT_DAMPING), "
                           "Nm s/rad: one value or one per joint; 0: none added (the default)"),
    "friction_coulomb": ([0.0, 0.0], "shared (/**): Coulomb joint friction [lo, hi], Nm, drawn per joint and episode "
                                     "from the reset seed (nf_core.friction); [0, 0]: off. Excludes joint_friction"),
    "friction_viscous": ([0.0, 0.0], "shared (/**): viscous joint friction [lo, hi] added to the arm's damping, "
                                     "Nm s/rad, drawn like friction_coulomb; [0, 0]: off. Excludes joint_viscous"),
    "seed": (-1, "start of the first episode: < 0 fixed start, else a sampled start"),
    "lockstep_resend": (0.1, "lockstep: s of wall time before an unanswered state is published again"),
    "task_status_rate": (50.0, "task_status messages per s of simulated time (0: off)"),
    "clock_period": (0.001, "s of simulated time between clock messages (0: every step)"),
    "monitor_period": (0.0, "composed only: s of simulated time between joint_states and applied-command messages "
                            "(0: every step; they are for monitoring and bags, the controller is called directly; "
                            "published only while subscribed)"),
    "monitor_always": (False, "composed only: publish joint_states, applied commands, clock and task_status even "
                              "without a subscriber (default: only while subscribed)"),
    "realtime_spin": (0.0003, "composed realtime: the last s of each 1 ms period waited awake without the GIL "
                              "instead of asleep (0: sleep only; costs up to that much CPU per period)"),
    "realtime_warm": (True, "composed realtime: before the spin, run the controller's compiled step on the last "
                            "state into scratch buffers so the next tick finds it in the caches (no effect on "
                            "torques)"),
    "rt_priority": (AUTO, "composed realtime: SCHED_FIFO priority of the driver thread (only): -1 auto (99 if the "
                          "system allows it, else normal scheduling), 0 normal, 1..99 required; lockstep and the "
                          "standalone bridge run at normal scheduling"),
    "diagnostics_period": (1.0, "s of wall time between /diagnostics messages"),
    "response_log": ("", "realtime: every latency to this .npy (+ .json summary) at shutdown; folder checked at start"),
}

# a number or a list (YAML [0, 0] is an integer array): checked by the env and nf_core.friction
DYNAMIC_PARAMETERS = ("joint_friction", "joint_viscous", "friction_coulomb", "friction_viscous")
_LATE_TICK = 2.0  # realtime: a tick later than this many periods counts as late
LISTENERS_PERIOD = 0.2  # s, composed: how often the driver thread looks up who subscribes to its monitoring
_ALL_LISTENED = (True, True, True, True)  # joint_states, applied commands, clock, task_status


def _check(p: dict) -> None:
    if p["task"] not in ("block", "free"):
        load_task(p["task"])  # TaskFileError (a ValueError) names what is wrong
    for name in ("lockstep_resend", "diagnostics_period"):
        if not p[name] > 0.0:
            raise ValueError(f"{name} must be > 0, got {p[name]}")
    for name in ("task_status_rate", "clock_period", "monitor_period"):
        if not p[name] >= 0.0:
            raise ValueError(f"{name} must be >= 0, got {p[name]}")
    if not 0.0 <= p["realtime_spin"] <= 0.0005:
        raise ValueError(f"realtime_spin must be between 0 and 0.0005 s (half a period), got {p['realtime_spin']}")
    if not AUTO <= p["rt_priority"] <= top_priority():
        raise ValueError(f"rt_priority must be -1 (auto), 0 (normal scheduling) or 1..{top_priority()}, "
                         f"got {p['rt_priority']}")
    if p["rt_priority"] > 0 and p["mode"] != "realtime":  # asked for, but it would set nothing: say so
        raise ValueError(f"rt_priority {p['rt_priority']} applies to the composed realtime loop only (mode "
                         f"realtime); lockstep runs at normal scheduling: leave it at -1 or set 0")
    if p["response_log"]:  # fail now, not after a long run when the log is written at shutdown
        folder = Path(p["response_log"]).parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"response_log: cannot create folder {folder}: {exc}") from None
        if not os.access(folder, os.W_OK):
            raise ValueError(f"response_log: folder {folder} is not writable")


class SimBridgeNode(Node):
    """Wires a ``SimBridge`` to ros2_control-style topics; see the module docstring."""

    def __init__(self, state_qos: QoSProfile = qos.STATE, host: LoopHost | None = None) -> None:
        super().__init__("sim_bridge")
        p = declare_read_only(self, PARAMETERS, dynamic=DYNAMIC_PARAMETERS)
        _check(p)
        config = BridgeConfig(mode=p["mode"], command_timeout=p["command_timeout"],
                              driver_gravity_compensation=p["driver_gravity_compensation"],
                              hold_damping=p["hold_damping"], hold_stiffness=p["hold_stiffness"])
        config.check()
        self.params = p
        env = InsertionEnv(p["task"], plane=p["block_plane"])
        env.set_joint_friction(p["joint_friction"], p["joint_viscous"])  # ValueError naming the parameter
        coulomb, damping = env.joint_friction
        friction = FrictionRanges(p["friction_coulomb"], p["friction_viscous"])  # ValueError naming the range
        if friction.enabled:
            if np.any(coulomb) or np.any(p["joint_viscous"]):
                raise ValueError("joint_friction / joint_viscous (fixed friction) and friction_coulomb / "
                                 "friction_viscous (drawn per episode) are both set: give one of them (the "
                                 "ranges [x, x] fix a value too)")
            env.set_friction_ranges(friction)
            self.get_logger().info(friction.describe())
        elif np.any(coulomb) or np.any(p["joint_viscous"]):
            self.get_logger().info(f"joint friction: Coulomb {np.round(coulomb, 4).tolist()} Nm, viscous (with "
                                   f"the arm's own damping) {np.round(damping, 4).tolist()} Nm s/rad")
        self.bridge = SimBridge(env, config)
        self.bridge.reset(seed=p["seed"])
        self.lockstep = p["mode"] == "lockstep"
        if host is None and p["rt_priority"] > 0:
            raise ValueError(f"rt_priority {p['rt_priority']} applies to the composed realtime loop only "
                             "(nf_sim_stack): the standalone bridge ticks on its executor")
        # the driver thread's scheduling, checked now (composed realtime only): never dropped silently
        rt_priority = 0 if host is None or self.lockstep else \
            loop_priority(p["rt_priority"], realtime_enforced=False, loop="the composed realtime loop")
        dt = self.bridge.dt
        self._status_every = max(1, round(1.0 / (p["task_status_rate"] * dt))) if p["task_status_rate"] else 0
        self._clock_every = max(1, round(p["clock_period"] / dt))
        self._monitor_every = max(1, round(p["monitor_period"] / dt)) if host is not None else 1

        self._state = JointState()
        self._state.name = list(self.bridge.joint_names)
        n = len(self._state.name)
        self._state.position, self._state.velocity, self._state.effort = [0.0] * n, [0.0] * n, [0.0] * n
        # the messages published every few steps (from the driver thread when composed), serialized
        # once and rewritten in place: no field setters and no conversion per publish
        self._state_raw = SerializedMessage(self._state, floats=("position", "velocity", "effort"),
                                            stamp="header.stamp")
        self._clock_msg = Clock()
        self._clock_raw = SerializedMessage(self._clock_msg, stamp="clock")
        self._state_pub = self.create_publisher(JointState, topics.JOINT_STATES, qos.PUBLISH)
        self._clock_pub = self.create_publisher(Clock, topics.CLOCK, qos.PUBLISH) if self.lockstep else None
        self._task_pub = self.create_publisher(TaskStatus, topics.TASK_STATUS, qos.PUBLISH)
        self._task_msg = TaskStatus(task=self.bridge.env.task, part_position=[0.0, 0.0, 0.0])
        self._task_msg.header.frame_id = "world"
        self._task_raw = SerializedMessage(self._task_msg, floats=("insertion_depth", "contact_force", "part_position"),
                                           bools=("success",), stamp="header.stamp")
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos.DIAGNOSTICS)
        self.create_service(ResetSim, "~/reset", self._on_reset)
        self.driver: SimDriverLoop | None = None
        if host is not None:
            self.driver = SimDriverLoop(self.bridge, host, realtime=not self.lockstep, after_step=self._after_step,
                                        keep_timing=bool(p["response_log"]), spin=p["realtime_spin"],
                                        warm=bool(p["realtime_warm"]), rt_priority=rt_priority,
                                        after_reset=self._after_reset)
            self._cmd = Float64MultiArray()
            self._cmd_dim = MultiArrayDimension(label=topics.stamp_label(0), size=n, stride=n)
            self._cmd.layout.dim = [self._cmd_dim]
            self._cmd.data = [0.0] * n
            self._cmd_raw = SerializedMessage(self._cmd, floats=("data",), texts=("layout.dim.0.label",))
            self._cmd_pub = self.create_publisher(Float64MultiArray, topics.COMMANDS, qos.PUBLISH)
            self._host = host
        else:
            on_command = self._on_command_lockstep if self.lockstep else self._on_command_realtime
            self.create_subscription(Float64MultiArray, topics.COMMANDS, on_command, state_qos)

        # composed: the monitoring messages (joint states, applied commands, clock, task status) go
        # out only while a topic has a subscriber; a headless learning run does not pay for them
        # (bench/bench_stack.py), a recorder or plot that subscribes gets them within LISTENERS_PERIOD
        self._listening = _ALL_LISTENED
        self._listeners_due = math.inf if p["monitor_always"] else 0.0
        self.monitor_skipped = 0  # monitoring messages not published for want of a subscriber
        self.resends = 0
        self.late_ticks = 0
        self._stale_reported = 0
        self._last_publish = time.monotonic()
        self._last_tick = None
        self._window = (time.monotonic(), 0, 0.0)  # wall time, steps, sim time at the last report
        self.timing = None if self.lockstep or host is not None else ResponseTiming(keep_all=bool(p["response_log"]))
        self._answers: int | None = None  # stamp the last command said it answers (parsed once, in _accept)
        if host is not None:
            pass  # the driver thread steps (start_driver)
        elif self.lockstep:
            self.create_timer(p["lockstep_resend"] / 2.0, self._on_resend_check)
        else:
            self.create_timer(dt, self._on_tick)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self._publish_state()
        self._publish_task_status()
        self.get_logger().info(
            f"{p['task']} scene, {p['mode']} mode{', composed with the controller' if host else ''}, "
            f"driver gravity compensation "
            f"{'on' if config.driver_gravity_compensation else 'off'}, joints {self._state.name}")

    # ------------------------------------------------------------------ composed: the driver thread
    def start_driver(self) -> None:
        """Composed: start stepping the world with the controller's torques on the driver thread."""
        if self.driver is not None:
            self.driver.start(self.get_logger())

    def stop_driver(self) -> None:
        """Composed: stop the driver thread (joins it)."""
        if self.driver is not None:
            self.driver.stop()

    def _publish_applied_command(self) -> None:
        """Composed: the command applied in the last step, labelled with the state it answered."""
        raw = self._cmd_raw
        raw.set_text("layout.dim.0.label", topics.stamp_label(self._host.last_stamp_ns))
        raw.floats["data"][:] = self._host.tau
        self._cmd_pub.publish(raw.payload())

    # ------------------------------------------------------------------ commands and steps
    def _on_command_lockstep(self, msg: Float64MultiArray) -> None:
        if not self._accept(msg):
            return
        self.bridge.step_commanded()
        self._after_step()

    def _on_command_realtime(self, msg: Float64MultiArray) -> None:
        now = time.perf_counter()
        if self._accept(msg) and self._answers is not None:
            self.timing.answered(self._answers, now)

    def _accept(self, msg: Float64MultiArray) -> bool:
        dims = msg.layout.dim
        answers = self._answers = parse_stamp_label(dims[0].label) if dims else None
        # Rejections are only counted here (logging one costs more than accepting a command, even
        # throttled): the diagnostics timer reports them.
        return self.bridge.accept_command(msg.data, time.monotonic(), answers) == ACCEPTED

    def _on_tick(self) -> None:
        now = time.monotonic()
        if self._last_tick is not None and now - self._last_tick > _LATE_TICK * self.bridge.dt:
            self.late_ticks += 1
        self._last_tick = now
        was_holding = self.bridge.in_hold
        holding = self.bridge.step_realtime(now)
        self._after_step()
        if holding != was_holding:
            if holding:
                self.get_logger().error(
                    f"no effort command for {self.params['command_timeout'] * 1e3:.0f} ms: safe hold "
                    f"(gravity compensation + joint damping), timeout #{self.bridge.command_timeouts}")
            else:
                self.get_logger().info("effort commands arrive again: leaving the safe hold")
            self._publish_diagnostics()

    def _after_step(self) -> None:
        steps = self.bridge.steps
        monitor = steps % self._monitor_every == 0
        clock = self._clock_pub is not None and steps % self._clock_every == 0
        task = self._status_every and steps % self._status_every == 0
        if not (monitor or clock or task):
            return
        state_on, cmd_on, clock_on, task_on = self._listeners() if self.driver is not None else _ALL_LISTENED
        skipped = 0
        if monitor:
            if self.driver is not None:
                if cmd_on:
                    self._publish_applied_command()
                else:
                    skipped += 1
            if state_on:
                self._publish_state()
            else:
                skipped += 1
        if clock:
            if clock_on:
                self._clock_raw.set_stamp(self.bridge.stamp_ns)
                self._clock_pub.publish(self._clock_raw.payload())
            else:
                skipped += 1
        if task:
            if task_on:
                self._publish_task_status()
            else:
                skipped += 1
        self.monitor_skipped += skipped

    def _after_reset(self) -> None:
        """Composed: the reset state (zero velocity and effort) to whoever listens, whatever the monitor
        period, as the separate node publishes it: a bag's episodes start there (``nf_bags.resim``)."""
        if self._listeners()[0]:
            self._publish_state()

    def _listeners(self) -> tuple[bool, bool, bool, bool]:
        """Composed: whether joint_states, the applied commands, clock and task_status have
        subscribers, looked up at most every LISTENERS_PERIOD s (driver thread)."""
        now = time.monotonic()
        if now >= self._listeners_due:
            self._listeners_due = now + LISTENERS_PERIOD
            self._listening = tuple(pub is not None and pub.get_subscription_count() > 0 for pub in
                                    (self._state_pub, self._cmd_pub, self._clock_pub, self._task_pub))
        return self._listening


    def _on_resend_check(self) -> None:
        if time.monotonic() - self._last_publish >= self.params["lockstep_resend"]:
            self.resends += 1
            self._publish_state()

    # ------------------------------------------------------------------ publishing
    def _publish_state(self) -> None:
        env, raw = self.bridge.env, self._state_raw
        raw.set_stamp(self.bridge.stamp_ns)
        raw.floats["position"][:] = env.q
        raw.floats["velocity"][:] = env.dq
        raw.floats["effort"][:] = self.bridge.effort
        if self.timing is not None:
            self.timing.published(self.bridge.stamp_ns, time.perf_counter())
        self._state_pub.publish(raw.payload())
        self._last_publish = time.monotonic()

    def _publish_task_status(self) -> None:
        env, raw = self.bridge.env, self._task_raw  # rewritten in place: this runs on the driver thread
        depth = env.insertion_depth
        raw.floats["insertion_depth"][0] = depth
        raw.set_bool("success", env.task != "free" and depth >= env.scene.success_depth)  # env.success, depth once
        force = env.contact_force
        raw.floats["contact_force"][0] = math.sqrt(float(force @ force))
        raw.set_stamp(self.bridge.stamp_ns)
        raw.floats["part_position"][:] = env.x
        self._task_pub.publish(raw.payload())

    def _publish_diagnostics(self) -> None:
        b = self.bridge
        report = b.take_error_report()
        if report:
            self.get_logger().error(report)
        if b.stale_commands != self._stale_reported:
            self.get_logger().warn(f"dropped {b.stale_commands - self._stale_reported} replies to an earlier state "
                                   f"({b.stale_commands} in all)")
            self._stale_reported = b.stale_commands
        now = time.monotonic()
        t0, steps0, sim0 = self._window
        wall = max(now - t0, 1e-9)
        self._window = (now, b.steps, b.sim_time)
        holding = not self.lockstep and b.in_hold
        status = DiagnosticStatus(name="sim_bridge: driver", hardware_id=f"mujoco:{b.env.task}")
        if holding and b.command_timeouts:
            status.level, status.message = DiagnosticStatus.WARN, "command timeout: safe hold"
        elif holding:
            status.level, status.message = DiagnosticStatus.OK, "waiting for the first command: safe hold"
        elif b.bad_commands:
            status.level, status.message = DiagnosticStatus.WARN, f"bad commands ignored: {b.last_error}"
        else:
            status.level, status.message = DiagnosticStatus.OK, "running"
        values = {
            "mode": self.params["mode"], "task": b.env.task, "sim_time": f"{b.sim_time:.4f}",
            "effort": "no-gravity" if b.config.driver_gravity_compensation else "applied",
            "steps": b.steps, "steps_per_s": f"{(b.steps - steps0) / wall:.1f}",
            "real_time_factor": f"{(b.sim_time - sim0) / wall:.3f}",
            "safe_hold": holding, "command_timeouts": b.command_timeouts, "hold_steps": b.hold_steps,
            "hold_delay_ms": f"{b.hold_delay * 1e3:.1f}",
            "bad_commands": b.bad_commands, "stale_commands": b.stale_commands, "last_error": b.last_error,
            "lockstep_resends": self.resends, "late_ticks": self.late_ticks,
        }
        if b.env.episode_friction is not None:  # this episode's draw (friction_coulomb / friction_viscous)
            values["episode_friction_coulomb"] = np.round(b.env.episode_friction[0], 4).tolist()
            values["episode_friction_viscous"] = np.round(b.env.episode_friction[1], 4).tolist()
        if self.timing is not None:
            lat = latency_summary(self.timing.take_window())
            values.update({f"response_{k}": f"{v:.1f}" for k, v in lat.items()})
            values.update(self.timing.counters())
        if self.driver is not None:
            values["loop_scheduling"] = self.driver.scheduling
            values["monitor_skipped"] = self.monitor_skipped
        timing = self.driver.timing if self.driver is not None else None
        if timing is not None:
            lat = latency_summary(timing.take_window())
            values.update({f"tick_{k}": f"{v:.1f}" for k, v in lat.items()})
            values.update(timing.counters())
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)

    def destroy_node(self) -> None:
        """Stop the driver thread (composed), write the response log (when asked for), then destroy the node."""
        self.stop_driver()
        if self.timing is not None and self.timing.all is not None:
            self.write_response_log(Path(self.params["response_log"]))
        if self.driver is not None and self.driver.timing is not None and self.params["response_log"]:
            self.write_tick_log(Path(self.params["response_log"]))
        super().destroy_node()

    def write_tick_log(self, path: Path) -> None:
        """Composed realtime: every state-to-command latency (s) to ``path`` (.npy), every tick period
        to ``<path>.periods.npy``, and the summary to ``path``.json."""
        timing = self.driver.timing
        lat = np.frombuffer(timing.latency, dtype=np.float64).copy()
        periods = np.frombuffer(timing.periods, dtype=np.float64).copy()
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, lat)
        np.save(path.with_suffix(".periods.npy"), periods)
        summary = {"composed": True, **latency_summary(timing.latency), "period": latency_summary(timing.periods),
                   **timing.counters(), "command_timeouts": self.bridge.command_timeouts,
                   "hold_steps": self.bridge.hold_steps, "steps": self.bridge.steps,
                   "long_late_runs": [{"at_s": round(t, 3), "ticks": n} for t, n in timing.long_runs]}
        path.with_suffix(".json").write_text(json.dumps(summary, indent=1))
        self.get_logger().info(f"tick log: {lat.size} latencies to {path}")

    def write_response_log(self, path: Path) -> None:
        """Every state-to-command latency (s) to ``path`` (.npy) and the counts to ``path``.json."""
        lat = np.frombuffer(self.timing.all, dtype=np.float64).copy()
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, lat)
        summary = {**latency_summary(lat), **self.timing.counters(), "command_timeouts": self.bridge.command_timeouts,
                   "hold_steps": self.bridge.hold_steps, "late_ticks": self.late_ticks, "steps": self.bridge.steps,
                   "long_miss_runs": [{"at_s": round(t, 3), "misses": n} for t, n in self.timing.long_runs]}
        path.with_suffix(".json").write_text(json.dumps(summary, indent=1))
        self.get_logger().info(f"response log: {lat.size} latencies to {path}")

    # ------------------------------------------------------------------ reset
    def _on_reset(self, request: ResetSim.Request, response: ResetSim.Response) -> ResetSim.Response:
        q = np.asarray(request.q, dtype=np.float64) if len(request.q) else None
        try:
            if self.driver is not None:  # composed: the world belongs to the driver thread
                obs = self._host.call(lambda: self.bridge.reset(seed=int(request.seed), q=q)).result(timeout=5.0)
            else:
                obs = self.bridge.reset(seed=int(request.seed), q=q)
        except (ValueError, RuntimeError, TimeoutError) as exc:
            response.success, response.message = False, str(exc)
            self.get_logger().error(f"reset refused: {exc}")
            return response
        response.success = True
        drawn = self.bridge.env.episode_friction
        if drawn is not None:  # the episode's joint friction (also in /diagnostics)
            self.get_logger().info(f"reset, seed {request.seed}: joint friction Coulomb "
                                   f"{np.round(drawn[0], 4).tolist()} Nm, viscous added "
                                   f"{np.round(drawn[1], 4).tolist()} Nm s/rad")
        response.q, response.x = obs.q.tolist(), obs.x.tolist()
        response.stamp_ns = self.bridge.stamp_ns
        self._publish_task_status()
        if self.lockstep:
            # Publish the reset state 1 ms after the reply, so the controller knows where its
            # episode starts before the state arrives (realtime: the next tick publishes it).
            self._defer(0.001, self._publish_state)
        return response

    def _defer(self, seconds: float, fn: object) -> None:
        """Call ``fn`` once after ``seconds`` of wall time."""

        def fire() -> None:
            timer.cancel()
            self.destroy_timer(timer)
            fn()

        timer = self.create_timer(seconds, fire)


def main(args: list[str] | None = None) -> int:
    """Console script ``sim_bridge``."""
    return run_node(SimBridgeNode, "sim_bridge", "MuJoCo Panda behind ros2_control-style topics "
                    "(joint_states, effort_controller/commands), lockstep or realtime.", args)


if __name__ == "__main__":
    raise SystemExit(main())
