"""nf_controller node: the stable flow controller between ``joint_states`` and
``effort_controller/commands`` (ros2_control conventions).

Episodes run through the ``run_episode`` action (nf_msgs/RunEpisode): wait for the requested
policy version, reset the world (the sim bridge's ``sim_bridge/reset`` service), run the
episode with held policy noise, stream the rollout on ``rollouts`` (nf_msgs/RolloutChunk, with
sequence numbers) and return the result. Between episodes ``idle_mode`` decides what the arm
gets: the safe hold (default), the deterministic controller, or (lockstep simulation) nothing.

Each joint state is answered within its own callback (EventsExecutor) with one torque command:
the flow controller, or the safe hold (gravity compensation + joint damping + a spring to where
the hold began, ``hold_stiffness``) on any bad input.
Policy parameters arrive on ``/policy_parameters`` (reliable, transient local), are validated
and swapped in between episodes. ``controller_status`` (50 Hz) and ``/diagnostics`` (1 Hz)
report mode, fault, energy and loop latency. ``~/clear_fault`` re-arms after a fault.
The checks and counters live in ``nf_controller_node.control_loop``.
"""

from __future__ import annotations

import array
import itertools
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future as ConcurrentFuture
from dataclasses import dataclass
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus, RolloutChunk, TaskStatus
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from nf_msgs.srv import ResetSim
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from nf_core import qos
from nf_core.episode import Chunk, EpisodeRun, EpisodeSpec, check_goal_duration
from nf_core.policy_params import PolicyLaw, PolicyParameterError, PolicyParameters
from nf_core.reward import DEFAULT_WEIGHTS
from nf_core.ros_runtime import declare_read_only, run_node
from nf_core.task_spec import HELD_PART_HELP, held_part_inertia
from nf_core.topics import (
    COMMANDS,
    CONTROLLER_STATUS,
    DIAGNOSTICS,
    JOINT_STATES,
    POLICY_PARAMETERS,
    ROLLOUTS,
    RUN_EPISODE,
    SIM_RESET,
    TASK_STATUS,
    TELEOP_TARGET,
    stamp_label,
)

from .arm_model import ArmModel
from .control_loop import MODE_IDLE, MODE_RESETTING, MODE_RUNNING, MODE_SAFE_HOLD, ControlLoop, LoopConfig
from .host import CHUNK, EPISODE_END, FAULT, ControllerHost, EpisodeDriver, success_of
from .stamp_gaps import StampGaps
from .torque_law import TorqueLawConfig

_LAW = TorqueLawConfig()
PARAMETERS = {
    "gravity_compensation": (True, "add g(q) to the torque; false when the driver compensates gravity (Franka)"),
    "driver_effort": ("measured", "what joint_states' effort is: measured (the joint torque, gravity included: "
                      "franka_ros2, libfranka tau_J) | command (the command applied, without the gravity the driver "
                      "adds: sim_bridge); a restarted controller ramps from its command part"),
    "held_part": ("gear", f"mass model and TCP of the part in the hand: {HELD_PART_HELP}"),
    "hold_damping": (_LAW.hold_damping, "joint damping of the safe hold, Nm s/rad"),
    "hold_stiffness": (_LAW.hold_stiffness, "Nm/rad of the safe hold's joint spring to where the hold began "
                       "(its anchor; 0: damping only, the arm coasts)"),
    "joint_limit_stiffness": (_LAW.joint_limit_stiffness, "Nm/rad of the springs that push a joint back from "
                              "its limit (0: off; conservative, so every policy stays stable)"),
    "joint_limit_margin": (_LAW.joint_limit_margin, "rad before a joint limit where its spring starts"),
    "deadline": (0.001, "s; a step taking longer is a deadline miss"),
    "max_consecutive_misses": (20, "deadline misses in a row that latch the safe hold (0: never)"),
    "state_timeout": (0.0, "s without a joint state before the safe hold (realtime drivers; 0: off)"),
    "status_rate": (50.0, "controller_status messages per s"),
    "idle_mode": ("hold", "between episodes: hold (safe hold) | policy (deterministic controller) | "
                  "pause (no answer: a lockstep sim waits)"),
    "reset_service": (SIM_RESET, "service that resets the world before an episode (empty: no reset)"),
    "decision_period": (0.01, "s; the policy noise is drawn once per period and held"),
    "control_period": (0.001, "s between joint states (1 kHz); standalone: stamp gaps longer than 1.5 "
                       "periods count the states missing in them (0: no count)"),
    "episode_seconds": (5.0, "default episode length when a goal asks for 0 s"),
    "chunk_decisions": (100, "decisions per streamed rollout chunk"),
    "policy_wait": (10.0, "s an episode waits for the policy version it asks for"),
    "reset_timeout": (60.0, "composed: s the driver may take to reset the world (a robot moves there)"),
    "diagnostics_period": (1.0, "s between /diagnostics messages"),
    "teleop_speed": (0.0, "m/s: an operator pulls the law's anchor x_ref towards the points on teleop/target "
                     "(geometry_msgs/PointStamped, base frame) at most this fast, from the TCP at each episode's "
                     "start; 0: off, x_ref is the policy's"),
}
DRIVER_EFFORTS = ("measured", "command")
# The law's settings that travel with the policy (nf_msgs/PolicyParameters): set here, they are ignored
POLICY_LAW_PARAMETERS = ("potential_force_bound", "k_rot", "d_rot", "joint_damping", "stiffness_floor")
_MODE_NAMES = {MODE_IDLE: "idle", MODE_RUNNING: "running", MODE_SAFE_HOLD: "safe_hold", MODE_RESETTING: "resetting"}


SETUP_POLL = 0.002  # s, how often a goal being set up looks at its policy version and reset
SERVICE_WAIT = 5.0  # s, standalone: longest wait for the sim's reset service to appear
# s, composed: the ticks' chunks, episode ends and faults are taken when the host queues them (the
# driver thread posts a task to the executor: rclpy's EventsExecutor has no guard conditions); this
# poll is only the fallback (every wake-up of the executor thread takes the GIL from the driver)
DRAIN_PERIOD = 0.25
MAX_FAULT_TEXT = 300  # characters of a fault reason in status, diagnostics and logs
BASE_FRAME = "panda_link0"


def _stamp(ns: int) -> Time:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def _goal_problem(goal: RunEpisode.Goal) -> str:
    """Why an episode goal cannot run ("" if it can). A duration of 0 means the default length."""
    try:
        check_goal_duration(goal.duration, 1.0)
    except ValueError as exc:
        return str(exc)
    return ""


def _loop_from(p: dict, arm: ArmModel | None = None, joint_names: Sequence[str] | None = None) -> ControlLoop:
    part = held_part_inertia(p["held_part"])  # ValueError names the choices
    if p["driver_effort"] not in DRIVER_EFFORTS:
        raise ValueError(f"driver_effort must be one of {DRIVER_EFFORTS}, got {p['driver_effort']!r}")
    for name in ("status_rate", "diagnostics_period"):
        if not p[name] > 0.0:
            raise ValueError(f"{name} must be > 0, got {p[name]}")
    law = TorqueLawConfig(hold_damping=p["hold_damping"], hold_stiffness=p["hold_stiffness"],
                          gravity_compensation=p["gravity_compensation"],
                          joint_limit_stiffness=p["joint_limit_stiffness"], joint_limit_margin=p["joint_limit_margin"])
    config = LoopConfig(deadline=p["deadline"], max_consecutive_misses=p["max_consecutive_misses"],
                        state_timeout=p["state_timeout"], idle_mode=p["idle_mode"])
    if not p["chunk_decisions"] >= 1:
        raise ValueError(f"chunk_decisions must be >= 1, got {p['chunk_decisions']}")
    if arm is None:
        arm = ArmModel(part=part)
    if joint_names is None:
        return ControlLoop(arm, law, config)
    return ControlLoop(arm, law, config, joint_names=joint_names)


@dataclass
class _Setup:
    """A RunEpisode goal being set up: waiting for its policy version, then for the world's reset."""

    gh: Any  # rclpy ServerGoalHandle
    duration: float  # s
    policy_deadline: float  # monotonic s
    run: EpisodeRun | None = None
    reset: Any = None  # composed: the driver's concurrent future; standalone: the reset service call
    reset_deadline: float = math.inf  # monotonic s: of the reset (composed) or of the service's appearance


class NFControllerNode(Node):
    """Wires a ``ControlLoop`` (behind a ``ControllerHost``) to ROS; see the module docstring.

    Standalone (default): the node is its own driver, answering every ``joint_states`` message with
    one ``effort_controller/commands`` message. ``composed=True``: a driver in the same process
    ticks ``self.host`` directly and is attached with ``attach_driver``; the node keeps the slow
    side (policy, episodes, rollouts, status, diagnostics, clear_fault). ``arm`` and
    ``joint_names`` let a driver give the model and joint names of the robot it is connected to.
    """

    def __init__(self, state_qos: QoSProfile = qos.STATE, policy_qos: QoSProfile = qos.POLICY, *,
                 composed: bool = False, arm: ArmModel | None = None,
                 joint_names: Sequence[str] | None = None, name: str = "nf_controller") -> None:
        super().__init__(name)
        p = declare_read_only(self, PARAMETERS)
        self.params = p
        # rclpy keeps every override given to the node (parameter files, -p), declared or not
        stale = sorted(set(getattr(self, "_parameter_overrides", {})) & set(POLICY_LAW_PARAMETERS))
        if stale:
            self.get_logger().warning(
                f"parameter(s) {', '.join(stale)} ignored: the law travels with the policy (nf_msgs/PolicyParameters, "
                "set in the learner's task file); the policy's values win")
        self.composed = composed
        self.loop = _loop_from(p, arm, joint_names)
        self.host = ControllerHost(self.loop)
        self._driver: EpisodeDriver | None = None
        self._status_pub = self.create_publisher(ControllerStatus, CONTROLLER_STATUS, state_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS, qos.DIAGNOSTICS)
        self.create_subscription(PolicyParametersMsg, POLICY_PARAMETERS, self._on_policy, policy_qos)
        self.create_service(Trigger, "~/clear_fault", self._on_clear_fault)
        self._chunk_pub = self.create_publisher(RolloutChunk, ROLLOUTS, qos.ROLLOUTS)
        self._reset_client = None
        if not p["teleop_speed"] >= 0.0:
            raise ValueError(f"teleop_speed must be >= 0 m/s (0: off), got {p['teleop_speed']}")
        if p["teleop_speed"] > 0.0:
            self.loop.controller.set_teleop(p["teleop_speed"], p["control_period"] or 0.001)
            self.create_subscription(PointStamped, TELEOP_TARGET, self._on_teleop_target, state_qos)
        if composed:
            self.host.notify = self._post_drain
            self.create_timer(DRAIN_PERIOD, self._drain)
        else:
            self._dim = MultiArrayDimension(label="", size=self.loop.n, stride=self.loop.n)
            self._cmd = Float64MultiArray()
            self._cmd.layout.dim = [self._dim]
            self._cmd_pub = self.create_publisher(Float64MultiArray, COMMANDS, qos.PUBLISH)
            self.create_subscription(JointState, JOINT_STATES, self._on_joint_state, state_qos)
            # what the keep-last reader overwrote (or the driver skipped): counted from the stamps
            self._gaps = StampGaps(p["control_period"])
            self._gaps_reported = 0
            self._reader_matched = False  # the driver's command reader (see _driver_listens)
            self._states_before_reader = 0
            self.create_subscription(TaskStatus, TASK_STATUS, self._on_task_status, state_qos)
            if p["reset_service"]:
                self._reset_client = self.create_client(ResetSim, p["reset_service"])
            if p["state_timeout"] > 0.0:
                self.create_timer(max(p["state_timeout"] / 4.0, 0.001), self._on_watchdog)
        self._weights = DEFAULT_WEIGHTS
        self._logged_law: PolicyLaw | None = None  # the law last logged with an installed policy
        self._episode_ids = itertools.count(int(time.time() * 1000) * 1000)  # unique across restarts
        self._episode_run: EpisodeRun | None = None
        self._goal = None
        self._resetting = False
        self._unanswered: JointState | None = None  # the last state left unanswered (see _release_states)
        self._rate_start_checked = False  # see _on_joint_state
        self._setup: _Setup | None = None  # the goal being set up (see _on_accepted)
        self._setup_timer = None
        self._result: RunEpisode.Result | None = None  # of the goal that ended, for _report
        ActionServer(self, RunEpisode, RUN_EPISODE, execute_callback=self._report, goal_callback=self._on_goal,
                     handle_accepted_callback=self._on_accepted, cancel_callback=self._on_cancel)
        self.create_timer(0.2, self._publish_feedback)
        self.create_timer(1.0 / p["status_rate"], self._publish_status)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self._sample = (float("nan"), float("nan"), None)  # V (J), dV/dt (W), TCP x (m) at the last state
        self._sample_future: ConcurrentFuture | None = None
        self.get_logger().info(
            f"flow controller up ({'composed with its driver' if composed else 'standalone, over topics'}): "
            f"gravity compensation {'on' if p['gravity_compensation'] else 'off (driver)'}, "
            f"held part {p['held_part']}, joints {list(self.loop.joints.joint_names)}; "
            f"holding until policy parameters arrive")

    def attach_driver(self, driver: EpisodeDriver) -> None:
        """Composed use: the driver that ticks ``self.host`` and resets its world for episodes."""
        self._driver = driver

    def _on_driver_thread(self, fn: Callable[[], object]) -> ConcurrentFuture:
        """Run ``fn`` where the ticks run: through the host when composed, here and now when standalone."""
        if self.composed:
            return self.host.call(fn)
        future: ConcurrentFuture = ConcurrentFuture()
        try:
            future.set_result(fn())
        except Exception as exc:
            future.set_exception(exc)
        return future

    # ------------------------------------------------------------------ standalone: the 1 kHz path
    def _on_joint_state(self, msg: JointState) -> None:
        stamp = msg.header.stamp
        stamp_ns = stamp.sec * 1_000_000_000 + stamp.nanosec
        self._gaps.observe(stamp_ns)
        if not self._reader_matched and not self._driver_listens():
            self._states_before_reader += 1
            if self._states_before_reader == 1:
                self.get_logger().warning(f"joint states arrive but no reader of {COMMANDS} has matched yet: "
                                          "no command until the driver listens")
            return  # a command now would be lost, and the driver would jump from its old one to a later one
        host, loop = self.host, self.loop
        host.service()
        if not loop.steps and not self._rate_start_checked:
            self._rate_start_checked = True  # once: the first state after start-up
            measured = self.params["driver_effort"] == "measured"
            why = loop.start_from_applied(msg.name, msg.effort, msg.position if measured else None)
            self.get_logger().info("torque rate limit starts from the applied torque the driver reports"
                                   if not why else f"torque rate limit starts unprimed: {why}")
        if not loop.answers(stamp_ns):
            self._unanswered = msg  # answered when the episode starts, if it is the reset state
            return
        tau = host.tick(stamp_ns, msg.position, msg.velocity, time.monotonic(), names=msg.name)
        self._dim.label = stamp_label(stamp_ns)  # lockstep handshake
        self._publish_command(tau)
        self._drain()

    def _driver_listens(self) -> bool:
        """Whether the driver's command reader has matched this node's publisher (looked at until it has,
        on every state and every diagnostics period)."""
        if self._cmd_pub.get_subscription_count() == 0:
            return False
        self._reader_matched = True
        self.get_logger().info(f"the driver's reader of {COMMANDS} matched: commanding from now on "
                               f"({self._states_before_reader} joint state(s) left unanswered before)")
        return True

    def _release_states(self) -> None:
        """End a reset: answer states again, first the one that came in meanwhile. Without this
        pause an idle hold could answer the reset state before the episode starts, and the sim
        would step the new world once with a hold torque (only when the reply and the state are
        handled out of order, i.e. on a busy machine). Answering the kept state at once saves the
        lockstep sim its resend wait."""
        self.loop.resetting = False
        held, self._unanswered = self._unanswered, None
        if held is not None and not self.composed:
            self._on_joint_state(held)

    def _publish_command(self, tau: np.ndarray) -> None:
        self._cmd.data = array.array("d", tau.tobytes())
        self._cmd_pub.publish(self._cmd)

    def _on_watchdog(self) -> None:
        tau, new_fault = self.loop.on_timer(time.monotonic())
        if tau is not None:
            self._dim.label = ""  # answers no state
            self._publish_command(tau)
        if new_fault:
            self.get_logger().error(f"safe hold: {new_fault}")

    def _on_task_status(self, msg: TaskStatus) -> None:
        self.loop.on_task_status(msg.insertion_depth, msg.success)  # checked; rejections are counted

    # ------------------------------------------------------------------ what the ticks produced
    def _post_drain(self) -> None:
        """Driver thread, when a tick queued events: have the executor drain them now."""
        executor = self.executor
        if executor is None:
            return
        try:
            executor.create_task(self._drain)
        except Exception:  # shutting down: the poll timer (or nobody) drains; never the tick's problem
            pass

    def _drain(self) -> None:
        """Publish the chunks, episode ends and faults the ticks produced (after each tick when
        standalone, from a timer when composed)."""
        for event in self.host.drain():
            if event.kind == CHUNK:
                self._publish_chunk(event.run, event.chunk, event.stamp_ns)
            elif event.kind == EPISODE_END:
                if event.run is self._episode_run:
                    self._episode_ended(event.text)
            elif event.kind == FAULT:
                self.get_logger().error(f"safe hold: {event.text}")

    def _publish_chunk(self, run: EpisodeRun, chunk: Chunk, stamp_ns: int) -> None:
        spec = run.spec
        msg = RolloutChunk(episode_id=spec.episode_id, seq=chunk.seq, final=chunk.final, n_chunks=chunk.n_chunks,
                           policy_version=spec.policy_version, dim=run.d)
        msg.header.stamp = _stamp(stamp_ns)
        msg.header.frame_id = BASE_FRAME
        for name in ("t", "x", "xdot", "u_mean", "action", "log_prob", "reward"):
            setattr(msg, name, array.array("d", np.ascontiguousarray(getattr(chunk, name)).tobytes()))
        msg.reward_terms = array.array("d", np.ascontiguousarray(chunk.terms).tobytes())
        msg.insertion_depth = array.array("d", chunk.depth.tobytes())
        self._chunk_pub.publish(msg)

    # ------------------------------------------------------------------ episodes
    def _on_goal(self, goal: RunEpisode.Goal) -> GoalResponse:
        if self._goal is not None:
            self.get_logger().error("episode goal rejected: another episode is running")
            return GoalResponse.REJECT
        problem = _goal_problem(goal)
        if problem:
            self.get_logger().error(f"episode goal rejected: {problem}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle: object) -> CancelResponse:
        self._end_episode_now("canceled")
        return CancelResponse.ACCEPT

    def _end_episode_now(self, problem: str) -> None:
        """End the running episode from the slow side (cancel, failure): on the driver thread."""
        run = self._episode_run
        if run is None:
            if self._setup is not None and self._result is None:  # still waiting for its policy
                self._stop_setup()
                self._finish(RunEpisode.Result(completed=False, message=problem))
            return
        self._stop_run(run, problem)
        if not self.composed:
            self._drain()
        self._episode_ended(problem)

    def _publish_feedback(self) -> None:
        run, gh = self.loop.episode, self._goal
        if run is None or gh is None:
            return
        gh.publish_feedback(RunEpisode.Feedback(t=run.t, lyapunov=self._sample[0], insertion_depth=self.host.depth,
                                                chunks_sent=run.chunks_sent))

    # An accepted goal runs without any coroutine: rclpy 7.1 resumes a coroutine that awaits a
    # pending future again at once, so a coroutine waiting through an episode kept the executor
    # thread resuming it and taking the GIL from the driver's ticks, and one waiting through a
    # Franka reset motion held the status timer back for up to 1.4 s on a loaded machine.
    # Instead: ``_on_accepted`` starts the set-up, which a SETUP_POLL timer advances (policy
    # version, then the world's reset: the driver's future or the reset service's answer) until the
    # episode runs; the episode's end (``_drain``), a cancel or a failure calls ``_episode_ended``,
    # which builds the result and only then executes the goal with ``_report`` (a plain function).
    # The goal is "accepted" while it is set up and runs, "executing" for an instant, then
    # succeeded, canceled or aborted.
    def _on_accepted(self, gh: object) -> None:
        self._goal = gh
        self._result = None
        try:
            duration = check_goal_duration(gh.request.duration, self.params["episode_seconds"])
        except ValueError as exc:  # checked when the goal was accepted: not expected
            self._finish(RunEpisode.Result(completed=False, message=str(exc)))
            return
        self._setup = _Setup(gh, duration, time.monotonic() + self.params["policy_wait"])
        self._setup_timer = self.create_timer(SETUP_POLL, self._advance_setup)
        self._advance_setup()

    def _advance_setup(self) -> None:
        setup = self._setup
        if setup is None:
            self._stop_setup()
            return
        try:
            problem = self._setup_step(setup)
        except Exception as exc:  # never leave an episode half-open: log, end it, report
            self.get_logger().error(f"episode failed: {exc!r}")
            problem = f"episode failed: {exc}"
            self._resetting = False
            if setup.run is not None:
                self._stop_run(setup.run, f"aborted: {exc}")
        if problem is None:  # still waiting
            return
        self._stop_setup()
        if problem and self._goal is setup.gh and self._result is None:
            self._finish(RunEpisode.Result(completed=False, message=problem))

    def _stop_setup(self) -> None:
        self._setup = None
        timer, self._setup_timer = self._setup_timer, None
        if timer is not None:
            timer.cancel()
            self.destroy_timer(timer)

    def _setup_step(self, setup: _Setup) -> str | None:
        """Advance ``setup``: None while it waits, "" once the episode runs, else why it cannot."""
        p, loop = self.params, self.loop
        goal = setup.gh.request
        if setup.run is not None:
            return self._poll_reset(setup)
        if not (loop.policy_version == goal.policy_version and loop.policy is not None):
            if time.monotonic() <= setup.policy_deadline:
                return None
            return (f"controller has policy version {loop.policy_version}, the episode asks for "
                    f"{goal.policy_version} (waited {p['policy_wait']:.0f} s)")
        if loop.fault:
            return f"safe hold: {loop.fault} (call {self.get_fully_qualified_name()}/clear_fault)"
        params = loop.policy
        sigma = None
        if not goal.deterministic:
            sigma = np.broadcast_to(np.exp(params.log_std), (params.arch.dim,)).copy()
        noise_seed = goal.noise_seed if goal.noise_seed >= 0 else goal.seed
        spec = EpisodeSpec(episode_id=next(self._episode_ids), policy_version=params.version,
                           duration=setup.duration, decision_period=p["decision_period"],
                           control_period=p["control_period"], sigma=sigma,
                           noise_seed=int(noise_seed) & 0x7FFFFFFFFFFFFFFF, x_goal=params.x_ref.copy(),
                           weights=self._weights, chunk_decisions=p["chunk_decisions"])
        setup.run = run = EpisodeRun(spec)
        self._episode_run = run
        self.host.set_task(float("nan"), False)
        if self.composed:  # the driver resets its world (sim: at once; robot: a motion), then starts run
            if self._driver is None:
                return "no driver attached to the composed controller"
            self._resetting = True
            setup.reset = self._driver.begin_episode(int(goal.seed), run)
            setup.reset_deadline = time.monotonic() + p["reset_timeout"]
        elif self._reset_client is not None:  # the sim's reset service, then the state it stamps
            self._resetting = True
            loop.resetting = True  # answer no state until the episode starts (see _release_states)
            setup.reset_deadline = time.monotonic() + SERVICE_WAIT
        else:  # no reset: from the next state on
            self.host.start_episode(run, 0, world_was_reset=False)
            self._release_states()
            return ""
        return self._poll_reset(setup)

    def _poll_reset(self, setup: _Setup) -> str | None:
        """The reset of ``setup``: None while it runs, "" once the episode runs, else the problem."""
        run, p = setup.run, self.params
        if self.composed:
            future = setup.reset
            if not future.done():
                if time.monotonic() <= setup.reset_deadline:
                    return None
                future.cancel()
                self._resetting = False
                return f"reset failed: the driver did not run the request within {p['reset_timeout']:.0f} s"
            self._resetting = False
            if future.exception() is not None:
                return f"reset failed: {future.exception()}"
        else:
            if setup.reset is None:  # the service first
                if not self._reset_client.service_is_ready():
                    if time.monotonic() <= setup.reset_deadline:
                        return None
                    return f"reset service {p['reset_service']} not available"
                setup.reset = self._reset_client.call_async(ResetSim.Request(seed=int(setup.gh.request.seed)))
                return None
            if not setup.reset.done():
                return None
            response = setup.reset.result()
            self._resetting = False
            if not response.success:
                return f"reset failed: {response.message}"
            if self._episode_run is run:
                self.host.start_episode(run, int(response.stamp_ns), world_was_reset=True)
            self._release_states()
        if self._episode_run is not run:  # canceled while the world was reset: already reported
            self._stop_run(run, "canceled")
        return ""

    def _stop_run(self, run: EpisodeRun, problem: str) -> None:
        """End ``run`` on the driver thread if it is the one running (no result: the caller reports)."""

        def end() -> None:
            if self.loop.episode is run:
                self.host.end_episode(problem)

        self._on_driver_thread(end)

    def _episode_ended(self, problem: str) -> None:
        """The running episode is over (``problem`` empty when it completed): report the goal."""
        run = self._episode_run
        if run is None or self._result is not None:
            return
        self._finish(self._episode_result(run, problem))

    def _finish(self, result: RunEpisode.Result) -> None:
        """End the goal with ``result``: clean up, then execute it (``_report`` gives the result)."""
        gh = self._goal
        self._result = result
        self._episode_run = None
        self._resetting = False
        self._release_states()  # a failed reset must not leave the states unanswered
        if gh is not None:
            gh.execute()

    def _report(self, gh: object) -> RunEpisode.Result:
        """Execute callback of a goal whose episode is already over: its terminal state and result."""
        result = self._result if self._result is not None else RunEpisode.Result(
            completed=False, message="episode ended without a result")
        self._goal = None
        self._result = None
        if result.completed:
            gh.succeed()
        elif gh.is_cancel_requested:
            gh.canceled()
        else:
            gh.abort()
            self.get_logger().error(f"episode not completed: {result.message}")
        return result

    def _episode_result(self, run: EpisodeRun, problem: str) -> RunEpisode.Result:
        spec = run.spec
        result = RunEpisode.Result(completed=not problem)
        result.episode_id = spec.episode_id
        result.n_chunks = run.chunks_sent
        result.episode_return = run.episode_return
        result.insertion_depth = float(self.host.depth)
        result.success = success_of(self.host.depth, self.host.success)
        if run.closed:  # at the state that closed the last closed decision (the last state when done)
            result.final_distance = run.final_distance
        result.torque_norm = run.mean_torque
        result.message = problem or f"{run.K} decisions, {run.chunks_sent} chunks"
        return result

    # ------------------------------------------------------------------ policy and faults
    def _on_policy(self, msg: PolicyParametersMsg) -> None:
        loop = self.loop
        old = loop.policy_version
        try:
            params = PolicyParameters.from_msg(msg)
            evaluator = loop.prepare_policy(params)  # the slow part, here on the executor thread
        except PolicyParameterError as exc:
            loop.policy_rejections += 1
            self.get_logger().error(f"rejected policy parameters version {msg.version}: {exc} "
                                    f"(keeping version {old})")
            return
        future = self._on_driver_thread(lambda: loop.set_policy(params, evaluator))
        a = params.arch
        what = f"n_flow={a.n_flow}, n_hidden={a.n_hidden}, {a.activation}, x_ref={params.x_ref.tolist()}"
        law = params.law
        if law != self._logged_law:  # each law once, with the first policy installed under it
            what += (f"; its law: force bound {law.potential_force_bound:g} N (0: off), k_rot {law.k_rot:g} Nm/rad, "
                     f"d_rot {law.d_rot:g} Nm s/rad, joint damping {law.joint_damping:g} Nm s/rad, "
                     f"stiffness floor {law.stiffness_floor:g} N/m, held part {law.held_part}")

        def report(f: ConcurrentFuture) -> None:
            try:
                now = f.result()
            except Exception as exc:  # PolicyParameterError from checks against the installed policy
                loop.policy_rejections += 1
                self.get_logger().error(f"rejected policy parameters version {params.version}: {exc}")
                return
            self._logged_law = law
            self.get_logger().info(f"policy version {params.version} "
                                   f"{'installed' if now else 'queued until the episode ends'}: {what}")

        future.add_done_callback(report)

    def _on_teleop_target(self, msg: PointStamped) -> None:
        p = msg.point
        try:
            self.loop.controller.set_teleop_target(np.array([p.x, p.y, p.z]))
        except ValueError as exc:
            self.get_logger().error(f"teleoperation target ignored, the anchor stays: {exc}",
                                    throttle_duration_sec=1.0)

    def _on_clear_fault(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        old = self.loop.fault if self.loop.controller.fault else ""
        self._on_driver_thread(self.loop.clear_fault)
        if not self.composed:
            self._gaps.restart()  # like the loop: the next state's stamp is the new time base
        response.success = True
        response.message = f"cleared: {old}" if old else "no fault latched"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------ reporting
    def _take_sample(self) -> tuple[float, float, np.ndarray | None]:
        """V, dV/dt and the TCP position at the last state: on the driver thread (they use the arm
        model the ticks use)."""
        loop = self.loop
        value, rate = loop.lyapunov()
        x = loop.controller.arm.tcp_position(loop.q) if loop.have_state else None
        return value, rate, x

    def _refresh_sample(self) -> None:
        """Standalone: sample now. Composed: take the sample asked for last time, ask for the next."""
        if not self.composed:
            self._sample = self._take_sample()
            return
        f = self._sample_future
        if f is not None and f.done():
            if f.exception() is None:
                self._sample = f.result()
            f = None
        if f is None:
            self._sample_future = self.host.call(self._take_sample)

    def _publish_status(self) -> None:
        loop = self.loop
        self._refresh_sample()
        value, rate, x = self._sample
        mode = MODE_RESETTING if self._resetting and not loop.fault else loop.mode
        msg = ControllerStatus(mode=mode, fault=loop.fault[:MAX_FAULT_TEXT], policy_version=loop.policy_version,
                               lyapunov=value, lyapunov_rate=rate, torque_norm=float(np.linalg.norm(self.host.tau)),
                               deadline_misses=loop.deadline_misses)
        msg.header.stamp = _stamp(self.host.last_stamp_ns)
        msg.header.frame_id = BASE_FRAME
        run = loop.episode
        if mode == MODE_RUNNING and run is None:  # the episode ended on the tick thread since the mode was read
            msg.mode = loop.mode
        if run is not None:
            msg.episode_id = run.spec.episode_id
        if x is not None:
            msg.x = x.tolist()
        if loop.policy is not None:  # while teleoperated: the anchor the operator pulls
            ref = loop.controller.reference if self.params["teleop_speed"] > 0.0 else None
            msg.x_ref = (loop.policy.x_ref if ref is None else ref).tolist()
        self._status_pub.publish(msg)
        report = loop.take_rejection_report()  # rejections are counted per message, logged only here
        if report:
            self.get_logger().error(f"{report}; holding: {loop.fault[:MAX_FAULT_TEXT]}")
        if not self.composed and self._gaps.missing > self._gaps_reported:
            new, self._gaps_reported = self._gaps.missing - self._gaps_reported, self._gaps.missing
            self.get_logger().warning(
                f"{new} joint state(s) never answered ({self._gaps.missing} in all, in {self._gaps.gaps} "
                f"stamp gaps): the driver skipped them or this node's keep-last reader overwrote them "
                f"while its executor was busy")

    def _publish_diagnostics(self) -> None:
        loop = self.loop
        lat = loop.latency.report()
        status = DiagnosticStatus(name=f"{self.get_name()}: control loop", hardware_id="panda")
        mode = loop.mode
        fault = loop.fault[:MAX_FAULT_TEXT]
        if mode == MODE_SAFE_HOLD:
            status.level = DiagnosticStatus.WARN if loop.policy is None else DiagnosticStatus.ERROR
            status.message = f"safe hold: {fault}"
        else:
            status.level, status.message = DiagnosticStatus.OK, _MODE_NAMES[mode]
        values = {
            "mode": _MODE_NAMES.get(mode, str(mode)), "fault": fault, "policy_version": loop.policy_version,
            "composed": self.composed, "steps": loop.steps, "steps_in_window": lat["count"],
            "latency_p50_us": f"{lat['p50_us']:.1f}", "latency_p90_us": f"{lat['p90_us']:.1f}",
            "latency_p99_us": f"{lat['p99_us']:.1f}", "latency_max_us": f"{lat['max_us']:.1f}",
            "deadline_misses": loop.deadline_misses, "faults": loop.faults, "bad_inputs": loop.bad_inputs,
            "policy_rejections": loop.policy_rejections, "task_status_rejected": loop.bad_task_status,
        }
        if not self.composed:  # the composed driver accounts for its own ticks
            if not self._reader_matched:
                self._driver_listens()
            values.update(states_missing=self._gaps.missing, stamp_gaps=self._gaps.gaps,
                          stamp_jumps=self._gaps.jumps, reader_matched=self._reader_matched,
                          states_before_reader=self._states_before_reader)
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

