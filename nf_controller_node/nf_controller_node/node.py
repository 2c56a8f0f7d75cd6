"""nf_controller node: the stable flow controller between ``joint_states`` and
``effort_controller/commands`` (ros2_control conventions).

Episodes run through the ``run_episode`` action (nf_msgs/RunEpisode): wait for the requested
policy version, reset the world (the sim bridge's ``sim_bridge/reset`` service), run the
episode with held policy noise, stream the rollout on ``rollouts`` (nf_msgs/RolloutChunk, with
sequence numbers) and return the result. Between episodes ``idle_mode`` decides what the arm
gets: the safe hold (default), the deterministic controller, or (lockstep simulation) nothing.

Each joint state is answered within its own callback (EventsExecutor) with one torque command:
the flow controller, or the safe hold (gravity compensation + joint damping) on any bad input.
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
from collections.abc import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus, RolloutChunk, TaskStatus
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from nf_msgs.srv import ResetSim
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from .arm_model import ArmModel
from .control_loop import MODE_IDLE, MODE_RESETTING, MODE_RUNNING, MODE_SAFE_HOLD, ControlLoop, LoopConfig
from .episode import Chunk, EpisodeRun, EpisodeSpec
from .panda_spec import GEAR_PART
from .policy_params import PolicyParameterError, PolicyParameters
from .reward import RewardWeights
from .ros_runtime import declare_read_only, run_node
from .topics import (
    COMMANDS,
    CONTROLLER_STATUS,
    DIAGNOSTICS,
    JOINT_STATES,
    POLICY_PARAMETERS,
    PUBLISH_DEPTH,
    ROLLOUTS,
    RUN_EPISODE,
    SIM_RESET,
    TASK_STATUS,
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
    "idle_mode": ("hold", "between episodes: hold (safe hold) | policy (deterministic controller) | "
                  "pause (no answer: a lockstep sim waits)"),
    "reset_service": (SIM_RESET, "service that resets the world before an episode (empty: no reset)"),
    "decision_period": (0.01, "s; the policy noise is drawn once per period and held"),
    "control_period": (0.001, "s between joint states (1 kHz)"),
    "episode_seconds": (5.0, "default episode length when a goal asks for 0 s"),
    "chunk_decisions": (100, "decisions per streamed rollout chunk"),
    "policy_wait": (10.0, "s an episode waits for the policy version it asks for"),
    "reward_w": (1.0, "reward: weight of |d|^2"),
    "reward_v": (2.0, "reward: weight of ln((|d|^2 + a) / a)"),
    "reward_a": (1.0e-5, "reward: offset a, m^2"),
    "reward_velocity": (0.1, "reward: weight of |xdot|^2"),
    "reward_action": (1.0e-3, "reward: weight of |u|^2"),
    "diagnostics_period": (1.0, "s between /diagnostics messages"),
}
STATE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
PUBLISH_QOS = QoSProfile(depth=PUBLISH_DEPTH, reliability=ReliabilityPolicy.RELIABLE)  # see topics.PUBLISH_DEPTH
POLICY_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
_MODE_NAMES = {MODE_IDLE: "idle", MODE_RUNNING: "running", MODE_SAFE_HOLD: "safe_hold", MODE_RESETTING: "resetting"}


class _Attrs:
    """Dict keys as attributes (the reward weights read a config object)."""

    def __init__(self, d: dict) -> None:
        self.__dict__.update(d)


def _loop_from(p: dict) -> ControlLoop:
    if p["held_part"] not in ("gear", "none"):
        raise ValueError(f"held_part must be 'gear' or 'none', got {p['held_part']!r}")
    for name in ("status_rate", "diagnostics_period"):
        if not p[name] > 0.0:
            raise ValueError(f"{name} must be > 0, got {p[name]}")
    law = TorqueLawConfig(k_rot=p["k_rot"], d_rot=p["d_rot"], joint_damping=p["joint_damping"],
                          hold_damping=p["hold_damping"], gravity_compensation=p["gravity_compensation"])
    config = LoopConfig(deadline=p["deadline"], max_consecutive_misses=p["max_consecutive_misses"],
                        state_timeout=p["state_timeout"], idle_mode=p["idle_mode"])
    if not p["chunk_decisions"] >= 1:
        raise ValueError(f"chunk_decisions must be >= 1, got {p['chunk_decisions']}")
    RewardWeights.from_config(_Attrs(p)).check()
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
        self._cmd_pub = self.create_publisher(Float64MultiArray, COMMANDS, PUBLISH_QOS)
        self._status_pub = self.create_publisher(ControllerStatus, CONTROLLER_STATUS, state_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS, state_qos)
        self.create_subscription(JointState, JOINT_STATES, self._on_joint_state, state_qos)
        self.create_subscription(PolicyParametersMsg, POLICY_PARAMETERS, self._on_policy, policy_qos)
        self.create_service(Trigger, "~/clear_fault", self._on_clear_fault)
        self.create_subscription(TaskStatus, TASK_STATUS, self._on_task_status, state_qos)
        self._chunk_pub = self.create_publisher(RolloutChunk, ROLLOUTS, QoSProfile(
            depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self._reset_client = self.create_client(ResetSim, p["reset_service"]) if p["reset_service"] else None
        self._weights = RewardWeights.from_config(_Attrs(p))
        self._episode_ids = itertools.count(int(time.time() * 1000) * 1000)  # unique across restarts
        self._episode_done: Future | None = None
        self._goal = None
        self._resetting = False
        self._unanswered: JointState | None = None  # the last state left unanswered (see _release_states)
        ActionServer(self, RunEpisode, RUN_EPISODE, execute_callback=self._execute,
                     goal_callback=self._on_goal, cancel_callback=self._on_cancel)
        self.create_timer(0.2, self._publish_feedback)
        self.create_timer(1.0 / p["status_rate"], self._publish_status)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        if p["state_timeout"] > 0.0:
            self.create_timer(max(p["state_timeout"] / 4.0, 0.001), self._on_watchdog)
        self._stamp = None
        self._task_success = False
        self._tau_norm = 0.0
        self._bad_logged = 0
        self.get_logger().info(
            f"flow controller up: gravity compensation {'on' if p['gravity_compensation'] else 'off (driver)'}, "
            f"joints {list(self.loop.joints.joint_names)}; holding until policy parameters arrive")

    # ------------------------------------------------------------------ the 1 kHz path
    def _on_joint_state(self, msg: JointState) -> None:
        t0 = time.perf_counter()
        stamp = msg.header.stamp
        stamp_ns = stamp.sec * 1_000_000_000 + stamp.nanosec
        loop = self.loop
        if not loop.answers(stamp_ns):
            self._unanswered = msg  # answered when the episode starts, if it is the reset state
            return
        tau, new_fault = loop.on_joint_state(msg.name, msg.position, msg.velocity, stamp_ns, time.monotonic())
        self._dim.label = stamp_label(stamp_ns)  # lockstep handshake
        self._publish_command(tau)
        self._stamp = stamp
        missed = loop.record_latency(time.perf_counter() - t0)
        if loop.episode is not None:
            self._episode_progress(loop.episode, new_fault or missed)
        if new_fault or missed:
            self.get_logger().error(f"safe hold: {new_fault or missed}")
        elif self.loop.bad_inputs != self._bad_logged:
            self.get_logger().error(f"bad joint state rejected ({self.loop.bad_inputs} so far); holding: "
                                    f"{self.loop.fault}", throttle_duration_sec=1.0)
        self._bad_logged = self.loop.bad_inputs

    def _release_states(self) -> None:
        """End a reset: answer states again, first the one that came in meanwhile. Without this
        pause an idle hold could answer the reset state before the episode starts, and the sim
        would step the new world once with a hold torque (only when the reply and the state are
        handled out of order, i.e. on a busy machine). Answering the kept state at once saves the
        lockstep sim its resend wait."""
        self.loop.resetting = False
        held, self._unanswered = self._unanswered, None
        if held is not None:
            self._on_joint_state(held)

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

    # ------------------------------------------------------------------ episodes
    def _episode_progress(self, run: EpisodeRun, fault: str) -> None:
        """After each answered state of an episode: stream finished chunks, end on done or fault."""
        for chunk in run.ready_chunks():
            self._publish_chunk(run, chunk)
        if fault or self.loop.fault:
            self._finish_episode(f"aborted: safe hold ({fault or self.loop.fault})")
        elif run.done:
            self._finish_episode("")

    def _finish_episode(self, problem: str) -> None:
        self.loop.end_episode()
        if self._episode_done is not None and not self._episode_done.done():
            self._episode_done.set_result(problem)

    def _publish_chunk(self, run: EpisodeRun, chunk: Chunk) -> None:
        spec = run.spec
        msg = RolloutChunk(episode_id=spec.episode_id, seq=chunk.seq, final=chunk.final, n_chunks=chunk.n_chunks,
                           policy_version=spec.policy_version, dim=run.d)
        if self._stamp is not None:
            msg.header.stamp = self._stamp
        msg.header.frame_id = "panda_link0"
        for name in ("t", "x", "xdot", "u_mean", "action", "log_prob", "reward"):
            setattr(msg, name, array.array("d", np.ascontiguousarray(getattr(chunk, name)).tobytes()))
        msg.reward_terms = array.array("d", np.ascontiguousarray(chunk.terms).tobytes())
        msg.insertion_depth = array.array("d", chunk.depth.tobytes())
        self._chunk_pub.publish(msg)

    def _on_goal(self, goal: RunEpisode.Goal) -> GoalResponse:
        if self._goal is not None:
            self.get_logger().error("episode goal rejected: another episode is running")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle: object) -> CancelResponse:
        self._finish_episode("canceled")
        return CancelResponse.ACCEPT

    def _publish_feedback(self) -> None:
        run, gh = self.loop.episode, self._goal
        if run is None or gh is None:
            return
        value, _ = self.loop.lyapunov()
        gh.publish_feedback(RunEpisode.Feedback(t=run.t, lyapunov=value, insertion_depth=self.loop.depth,
                                                chunks_sent=run.chunks_sent))

    def _sleep(self, seconds: float) -> Future:
        """A future done after ``seconds`` (for ``await`` in the action's coroutine)."""
        future = Future()

        def fire() -> None:
            timer.cancel()
            self.destroy_timer(timer)
            future.set_result(None)

        timer = self.create_timer(seconds, fire)
        return future

    async def _wait_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return False
            await self._sleep(0.01)
        return True

    async def _execute(self, gh: object) -> RunEpisode.Result:
        self._goal = gh
        try:
            result = await self._run_episode(gh.request)
        except Exception as exc:  # never leave an episode half-open: log, end it, report
            self.get_logger().error(f"episode failed: {exc!r}")
            self._finish_episode(f"aborted: {exc}")
            result = RunEpisode.Result(completed=False, message=f"episode failed: {exc}")
        finally:
            self._goal = None
            self._resetting = False
            self._release_states()  # a failed reset must not leave the states unanswered
        if result.completed:
            gh.succeed()
        elif gh.is_cancel_requested:
            gh.canceled()
        else:
            gh.abort()
            self.get_logger().error(f"episode not completed: {result.message}")
        return result

    async def _run_episode(self, goal: RunEpisode.Goal) -> RunEpisode.Result:
        p, loop = self.params, self.loop
        result = RunEpisode.Result(completed=False)
        duration = goal.duration if goal.duration > 0.0 else p["episode_seconds"]
        if not await self._wait_until(lambda: loop.policy_version == goal.policy_version and loop.policy is not None,
                                      p["policy_wait"]):
            result.message = (f"controller has policy version {loop.policy_version}, the episode asks for "
                              f"{goal.policy_version} (waited {p['policy_wait']:.0f} s)")
            return result
        if loop.fault:
            result.message = f"safe hold: {loop.fault} (call nf_controller/clear_fault)"
            return result
        first_stamp = 0
        if self._reset_client is not None:
            self._resetting = True
            loop.resetting = True  # answer no state until the episode starts (see _release_states)
            if not await self._wait_until(self._reset_client.service_is_ready, 5.0):
                result.message = f"reset service {p['reset_service']} not available"
                return result
            response = await self._reset_client.call_async(ResetSim.Request(seed=int(goal.seed)))
            self._resetting = False
            if not response.success:
                result.message = f"reset failed: {response.message}"
                return result
            first_stamp = int(response.stamp_ns)
        params = loop.policy
        sigma = None
        if not goal.deterministic:
            sigma = np.broadcast_to(np.exp(params.log_std), (params.arch.dim,)).copy()
        noise_seed = goal.noise_seed if goal.noise_seed >= 0 else goal.seed
        spec = EpisodeSpec(episode_id=next(self._episode_ids), policy_version=params.version, duration=duration,
                           decision_period=p["decision_period"], control_period=p["control_period"], sigma=sigma,
                           noise_seed=int(noise_seed) & 0x7FFFFFFFFFFFFFFF, x_goal=params.x_ref.copy(),
                           weights=self._weights, chunk_decisions=p["chunk_decisions"])
        run = EpisodeRun(spec)
        self._episode_done = Future()
        loop.depth = float("nan")
        loop.start_episode(run, first_stamp)
        self._release_states()
        problem = await self._episode_done
        result.episode_id = spec.episode_id
        result.n_chunks = run.chunks_sent
        result.episode_return = run.episode_return
        result.insertion_depth = float(self.loop.depth)
        result.success = bool(self._task_success) if math.isfinite(self.loop.depth) else False
        if run.closed:
            result.final_distance = float(np.linalg.norm(run.x[run.closed - 1] - spec.x_goal))
        if run.done and self.loop.have_state:
            result.final_distance = float(np.linalg.norm(self.loop.controller.arm.x - spec.x_goal))
        result.torque_norm = run.mean_torque
        result.completed = not problem
        result.message = problem or f"{run.K} decisions, {run.chunks_sent} chunks"
        return result

    def _on_task_status(self, msg: TaskStatus) -> None:
        self.loop.depth = float(msg.insertion_depth)
        self._task_success = bool(msg.success)

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
        mode = MODE_RESETTING if self._resetting and not loop.fault else loop.mode
        msg = ControllerStatus(mode=mode, fault=loop.fault, policy_version=loop.policy_version,
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

