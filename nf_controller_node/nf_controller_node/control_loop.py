"""ROS-free core of ``nf_controller_node``: joint state in, joint torque out, with every check the
node needs (joint names, sizes, stamp order, stale state, deadline misses, policy swaps).

``ControlLoop.on_joint_state`` runs once per joint state and always returns a finite torque
(the flow controller, or the safe hold on any problem). Faults latch in the
``FlowController`` until ``clear_fault``; ``mode`` and ``fault`` say what is being commanded.

Bad input is cheap: a rejected message is counted and its reason kept (``take_rejection_report``
gives the node one line to log from a slow timer), never logged from the 1 kHz path. Fault and
rejection texts are bounded (``FAULT_TEXT_MAX``), whatever the message carried.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from nf_core.episode import EpisodeRun, check_task_depth
from nf_core.flow_spec import FlowArchitecture
from nf_core.panda_spec import (
    DQ_PLAUSIBLE_FACTOR,
    DQ_PLAUSIBLE_MAX,
    JOINT_NAMES,
    Q_MAX,
    Q_MIN,
    Q_PLAUSIBLE_MARGIN,
    Q_PLAUSIBLE_MAX,
    Q_PLAUSIBLE_MIN,
)
from nf_core.policy_params import POLICY_LIMITS, PolicyLimits, PolicyParameterError, PolicyParameters
from nf_core.tick_timing import latency_summary

from .arm_model import ArmModel
from .controller import (
    DQ_IMPLAUSIBLE,
    DQ_NOT_FINITE,
    PROBLEM_BASE,
    Q_IMPLAUSIBLE,
    Q_NOT_FINITE,
    FlowController,
    state_problem,
)
from .flow_eval import FlowEvaluator
from .lyapunov import LyapunovMonitor
from .torque_law import TorqueLawConfig, excess_norm

# ControllerStatus modes (same numbers as nf_msgs/msg/ControllerStatus).
MODE_IDLE, MODE_RUNNING, MODE_SAFE_HOLD, MODE_RESETTING = 0, 1, 2, 3
NO_POLICY = "waiting for policy parameters"
# Between episodes: "hold" answers every state with the safe hold (gravity + joint damping + the
# hold spring to where the hold began; for realtime drivers and hardware), "policy" runs the
# deterministic controller, "pause" does not answer at all (a lockstep simulator then waits
# instead of burning CPU during the PPO update).
IDLE_MODES = ("hold", "policy", "pause")
FAULT_TEXT_MAX = 300  # characters: longest fault or rejection text the loop keeps, publishes or logs
_PREVIEW_NAMES = 3  # names shown in a bad-names reason
_PREVIEW_NAME_CHARS = 40  # characters shown of each


def bound_text(text: str, limit: int = FAULT_TEXT_MAX) -> str:
    """``text`` cut to at most ``limit`` characters, saying how many were dropped."""
    if len(text) <= limit:
        return text
    tail = f"... [+{len(text) - limit} chars]"
    return text[: max(0, limit - len(tail))] + tail


def _names_preview(names: Sequence[str]) -> str:
    """A few names (each cut short) and how many more: bounded whatever ``names`` holds."""
    shown = [repr(str(n)[:_PREVIEW_NAME_CHARS]) for n in names[:_PREVIEW_NAMES]]
    more = len(names) - len(shown)
    return "[" + ", ".join(shown) + (f", ... and {more} more" if more > 0 else "") + "]"


class JointStateError(ValueError):
    """A joint state message that cannot be used (names, sizes)."""


class JointMap:
    """Maps a JointState's name order onto the controller's joint order (cached per name list)."""

    def __init__(self, joint_names: Sequence[str] = JOINT_NAMES) -> None:
        self.joint_names = tuple(joint_names)
        self._names: list[str] | None = None
        self._bad_names: list[str] | None = None  # the last list that failed, and why
        self._bad_text = ""
        self._index = np.arange(len(self.joint_names))
        self._identity = True  # the last good name list is the controller's order: no reindexing
        self._same: tuple[str, ...] | None = None  # a tuple already mapped (immutable: no recheck)

    def _build(self, names: list[str]) -> np.ndarray:
        expected = list(self.joint_names)
        if len(names) > 4 * len(expected):  # do not scan or print a huge list: its size is reason enough
            raise JointStateError(f"unknown joint name(s): {len(names)} names for {len(expected)} joints")
        known = set(self.joint_names)
        unknown = [n for n in names if n not in known]
        if unknown:
            raise JointStateError(f"unknown joint name(s) {_names_preview(unknown)}; expected {expected}")
        if len(set(names)) != len(names):
            raise JointStateError(f"duplicate joint names in {_names_preview(names)}")
        missing = [n for n in self.joint_names if n not in names]
        if missing:
            raise JointStateError(f"missing joint(s) {missing}")
        return np.array([names.index(n) for n in self.joint_names])

    def map(self, names: Sequence[str], position: Sequence[float], velocity: Sequence[float]
            ) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) in controller order; ``JointStateError`` for unknown/missing names or wrong sizes.
        A driver that hosts the controller passes the same name tuple every tick: it is checked once."""
        if names is self._same and len(position) == len(names) and len(velocity) == len(names):
            if self._identity:
                return np.asarray(position, dtype=np.float64), np.asarray(velocity, dtype=np.float64)
            return (np.asarray(position, dtype=np.float64)[self._index],
                    np.asarray(velocity, dtype=np.float64)[self._index])
        if len(names) > 4 * len(self.joint_names):
            self._build(names)  # raises, without copying the list
        names_in, names = names, list(names)
        if names != self._names:
            if names == self._bad_names:  # the same bad list again (a flood): no rebuild, no new text
                raise JointStateError(self._bad_text)
            try:
                self._index = self._build(names)
            except JointStateError as exc:
                self._bad_names, self._bad_text = names, str(exc)
                raise
            self._names = names
            self._identity = bool(np.array_equal(self._index, np.arange(len(self.joint_names))))
        n = len(names)
        if len(position) != n or len(velocity) != n:
            raise JointStateError(f"{n} names but {len(position)} positions and {len(velocity)} velocities")
        q = np.asarray(position, dtype=np.float64)[self._index]
        dq = np.asarray(velocity, dtype=np.float64)[self._index]
        self._same = names_in if isinstance(names_in, tuple) else None
        return q, dq


class LatencyStats:
    """Loop latencies (s) since the last ``report``: percentiles and count."""

    def __init__(self, capacity: int = 16384) -> None:
        self._buf = np.zeros(capacity)
        self._n = 0
        self.total = 0

    def add(self, seconds: float) -> None:
        """Record one latency (the oldest entries of a full window are overwritten)."""
        self._buf[self._n % self._buf.size] = seconds
        self._n += 1
        self.total += 1

    def report(self) -> dict[str, float]:
        """``latency_summary`` of the window (microseconds), with the count of every latency since the
        last report (a full window keeps only the newest); starts a new window."""
        n = min(self._n, self._buf.size)
        count = self._n
        self._n = 0
        return {**latency_summary(self._buf[:n]), "count": count}


class _NoPolicy:
    """Stand-in evaluator before the first policy arrives: any use of it holds the arm."""

    def force(self, x: np.ndarray, xdot: np.ndarray, out: np.ndarray) -> None:
        raise ValueError(NO_POLICY)

    def potential(self, x: np.ndarray) -> float:
        return float("nan")


@dataclass
class LoopConfig:
    """Settings of the control loop. Units: s."""

    deadline: float = 0.001  # a step taking longer than this is a deadline miss
    max_consecutive_misses: int = 20  # this many misses in a row latch the safe hold (0: never)
    state_timeout: float = 0.0  # realtime use: no joint state for this long latches the safe hold (0: off)
    idle_mode: str = "policy"  # between episodes: policy (deterministic controller) | hold | pause

    def check(self) -> None:
        """Raise ``ValueError`` naming the first bad value."""
        if self.idle_mode not in IDLE_MODES:
            raise ValueError(f"idle_mode must be one of {IDLE_MODES}, got {self.idle_mode!r}")
        self._check_times()

    def _check_times(self) -> None:
        if not self.deadline > 0.0:
            raise ValueError(f"deadline must be > 0 s, got {self.deadline}")
        if self.max_consecutive_misses < 0:
            raise ValueError(f"max_consecutive_misses must be >= 0, got {self.max_consecutive_misses}")
        if not self.state_timeout >= 0.0:
            raise ValueError(f"state_timeout must be >= 0 s, got {self.state_timeout}")


class ControlLoop:
    """Joint states to torques through a ``FlowController``; owns the policy and the fault counters."""

    def __init__(self, arm: ArmModel, law: TorqueLawConfig | None = None, config: LoopConfig | None = None,
                 joint_names: Sequence[str] = JOINT_NAMES, limits: PolicyLimits = POLICY_LIMITS) -> None:
        self.config = config or LoopConfig()
        self.config.check()
        self.joints = JointMap(joint_names)
        self.controller = FlowController(arm, _NoPolicy(), law)  # type: ignore[arg-type]
        self.limits = limits  # bounds on the policies set_policy installs
        self.policy: PolicyParameters | None = None
        self._pending: tuple[PolicyParameters, FlowEvaluator] | None = None
        self.episode_active = False
        self.episode: EpisodeRun | None = None
        self._episode_from = 0  # ns: the episode starts at the first state stamped at or after this
        self._episode_last = -1  # ns: stamp of the last state the episode consumed
        self.episode_start_ns = 0  # ns: stamp of the running (or last) episode's first state
        self._episode_world_reset = False  # the episode's first command may skip the rate limit
        self.resetting = False  # the world is being reset for an episode: answer no state
        self._episode_eps = np.zeros(3)
        self._episode_tau = np.zeros(arm.nq)  # command sent for the last state of the episode
        self._no_gravity = np.zeros(arm.nq)  # what the command holds of g(q) when the driver compensates it
        self._u_mean = np.zeros(3)
        self.depth = float("nan")  # latest insertion depth from the simulator's task status (m), if any
        self.task_success = False  # latest success flag of the task status
        self.latency = LatencyStats()
        self.monitor = LyapunovMonitor(dt=0.02, tolerance=1e-3, time_constant=0.1)
        self._lyapunov_time: float | None = None  # clock (s) of the monitor's last sample
        self.n = arm.nq
        self.q = np.zeros(self.n)  # last valid joint state (rad, rad/s)
        self.dq = np.zeros(self.n)
        # plausible joint states (panda_spec): beyond these a reading faults in every mode
        self.q_min, self.q_max = Q_PLAUSIBLE_MIN.copy(), Q_PLAUSIBLE_MAX.copy()
        self.dq_max = DQ_PLAUSIBLE_MAX.copy()
        self.have_state = False
        self.last_state_time = -np.inf  # wall time (s) of the last joint state
        self._watchdog_time = -np.inf  # wall time (s) of the watchdog's previous run
        self._last_stamp = -1  # ns, stamp of the last accepted state (-1: take any)
        self.steps = 0
        self.bad_inputs = 0  # joint states rejected (names, sizes, stamps, values)
        self._rejection: tuple = ()  # why the latest one was rejected, formatted only when read
        self.bad_task_status = 0  # task status messages rejected
        self.last_task_status_error = ""
        self._reported = (0, 0)  # (bad_inputs, bad_task_status) at the last take_rejection_report
        self.faults = 0  # times a fault latched
        self.deadline_misses = 0
        self._consecutive_misses = 0
        self.policy_rejections = 0
        self._nan = np.full(self.n, np.nan)
        self._warm_up(arm)

    def _warm_up(self, arm: ArmModel) -> None:
        """Load the compiled kernels now (about 0.3 s), so the first policy swap and the first
        flow step cost a millisecond instead of stalling a running loop."""
        arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=4, activation="gelu")
        params = PolicyParameters(arch, np.zeros(arch.n_params), np.zeros(1), np.eye(3), np.eye(3), np.zeros(3))
        scratch = FlowController(arm, FlowEvaluator.from_params(params), self.controller.law)
        q = 0.5 * (Q_MIN + Q_MAX)
        scratch.step(q, np.zeros(self.n))
        scratch.hold(q, np.zeros(self.n))  # the first fault must not stall on loading the hold kernel
        scratch.lyapunov(q, np.zeros(self.n))
        state_problem(q, q, self.q_min, self.q_max, self.dq_max)

    # ------------------------------------------------------------------ status
    @property
    def fault(self) -> str:
        """Why the loop holds the arm ("" when it runs the flow controller)."""
        if self.controller.fault:
            return self.controller.fault
        return NO_POLICY if self.policy is None else ""

    @property
    def mode(self) -> int:
        """MODE_SAFE_HOLD, MODE_RUNNING or MODE_IDLE."""
        if self.fault:
            return MODE_SAFE_HOLD
        return MODE_RUNNING if self.episode_active else MODE_IDLE

    @property
    def policy_version(self) -> int:
        """Version of the policy in use (0 before any)."""
        return self.policy.version if self.policy is not None else 0

    def _latch(self, reason: str) -> bool:
        """Latch a fault (text bounded); True if this is a new one (the caller logs it)."""
        if self.controller.fault:
            return False
        self.controller.fault = bound_text(reason)
        self.faults += 1
        return True

    def clear_fault(self) -> str:
        """Re-arm after a fault; returns the fault that was cleared.

        The loop also forgets the stamp of the last accepted state: the next state's stamp is the
        new time base. Otherwise one state stamped far in the future (or a driver restarted with
        its clock back at zero) would make every later state "out of order" again, forever.
        """
        old = self.controller.fault
        self.controller.clear_fault()  # and drops the hold's anchor: the next hold anchors where the arm is
        self._consecutive_misses = 0
        self._last_stamp = -1
        return old

    @property
    def last_rejection(self) -> str:
        """Why the latest rejected joint state was rejected ("" if none was), bounded."""
        return bound_text(self._rejection_text(self._rejection)) if self._rejection else ""

    def take_rejection_report(self) -> str | None:
        """One bounded line about the messages rejected since the last call (None if there were
        none): for the node to log from a slow timer instead of logging on the 1 kHz path."""
        seen = (self.bad_inputs, self.bad_task_status)
        if seen == self._reported:
            return None
        n_state, n_task = seen[0] - self._reported[0], seen[1] - self._reported[1]
        self._reported = seen
        parts = []
        if n_state:
            parts.append(f"{n_state} joint state(s) rejected ({seen[0]} in all), last: {self.last_rejection}")
        if n_task:
            parts.append(f"{n_task} task status message(s) rejected ({seen[1]} in all), last: "
                         f"{self.last_task_status_error}")
        return bound_text("; ".join(parts), 2 * FAULT_TEXT_MAX)

    # ------------------------------------------------------------------ policy
    def prepare_policy(self, params: PolicyParameters) -> FlowEvaluator:
        """Check ``params`` against this arm and ``self.limits`` and build their evaluator: the slow,
        state-free part of a swap (call it off the tick thread). Raises ``PolicyParameterError``."""
        if params.arch.dim != 3:
            raise PolicyParameterError(f"the arm needs a 3-D flow, got dim={params.arch.dim}")
        held = self.controller.arm.held_part
        if params.law.held_part != held:
            raise PolicyParameterError(f"the policy was learned with held_part {params.law.held_part!r}; this "
                                       f"controller's hand holds {held!r} (its held_part parameter)")
        params.check_limits(self.limits, reach=True)
        try:
            return FlowEvaluator.from_params(params)
        except ValueError as exc:
            raise PolicyParameterError(bound_text(f"flow evaluator: {exc}")) from None

    def set_policy(self, params: PolicyParameters, evaluator: FlowEvaluator | None = None) -> bool:
        """Validate and install new parameters: now (True) or, during an episode, at its end (False).

        Raises ``PolicyParameterError`` when they do not fit this arm, are beyond ``self.limits``
        (noise, S, D, weights, flow size, x_ref out of reach), or their version is older than the
        installed (or queued) one; re-sending the same version is fine. ``evaluator`` from
        ``prepare_policy`` skips the checks and the build done there.
        """
        newest = max(self.policy.version if self.policy is not None else -1,
                     self._pending[0].version if self._pending is not None else -1)
        if params.version < newest:
            raise PolicyParameterError(
                f"version {params.version} is older than version {newest} already installed or queued "
                "(versions must not go backwards; a new learner run needs a restarted controller)")
        if evaluator is None:
            evaluator = self.prepare_policy(params)
        if self.episode_active:
            self._pending = (params, evaluator)
            return False
        self._install(params, evaluator)
        return True

    def _install(self, params: PolicyParameters, evaluator: FlowEvaluator) -> None:
        self.controller.set_evaluator(evaluator)
        self.controller.set_policy_law(params.law)  # the policy's gains and force bound
        self.policy = params
        self._pending = None
        self.monitor.reset()
        self._lyapunov_time = None

    def start_episode(self, run: EpisodeRun, first_stamp_ns: int = 0, world_was_reset: bool = False) -> None:
        """Run ``run`` from the first joint state stamped at or after ``first_stamp_ns`` (the reset state).

        ``world_was_reset``: a simulator teleported the arm to the start for this episode, so the
        torque sent before no longer acts on anything and the episode's first command starts
        without a rate limit (as the trainer's in-process rollout does). Default False: the torque
        rate limit holds at every tick, the first of the episode included (hardware, no reset).
        Raises ``ValueError`` without a policy, with a latched fault or while another episode runs.
        """
        if self.policy is None:
            raise ValueError(NO_POLICY)
        if self.controller.fault:
            raise ValueError(f"safe hold: {self.controller.fault}")
        if self.episode is not None:
            raise ValueError("an episode is already running")
        self.episode = run
        self.controller.engage_teleop()
        self._episode_from = int(first_stamp_ns)
        self._episode_last = -1
        self.episode_start_ns = 0  # stamp of the episode's first state, once it has one
        self._episode_world_reset = bool(world_was_reset)
        self.episode_active = True

    def end_episode(self) -> EpisodeRun | None:
        """Mark the episode over (done or aborted), install parameters that arrived during it, and
        return its record."""
        run, self.episode = self.episode, None
        self.episode_active = False
        if self._pending is not None:
            self._install(*self._pending)
        return run

    # ------------------------------------------------------------------ task status
    def on_task_status(self, depth: float, success: bool) -> str:
        """Take the simulator's task status (insertion depth in m, success): "" when used, else the
        reason it was rejected (counted, kept for ``take_rejection_report``; depth and success
        keep their previous values, so a spoofed depth never reaches a record or a result)."""
        try:
            value = check_task_depth(depth)
        except ValueError as exc:
            self.bad_task_status += 1
            self.last_task_status_error = reason = bound_text(str(exc))
            return reason
        self.depth = value
        self.task_success = bool(success)
        return ""

    def start_from_applied(self, names: Sequence[str], effort: Sequence[float],
                           position: Sequence[float] | None = None) -> str:
        """Start the torque rate limit from the torque the arm is applying (``effort`` of the driver's
        first joint state, Nm, in the state's name order), not from nothing: a controller restarted
        under a running driver then ramps from the command the arm still holds. ``position`` (rad, the
        same state's): the effort is the joint torque the arm measures, gravity included (franka_ros2,
        libfranka's tau_J); when the driver adds gravity itself, g(q) is taken off, leaving the command's
        part. None: the effort is the command the driver applies, without the gravity it adds (our
        simulator). Only before the first command; an effort that is missing, of the wrong size, not
        finite or beyond the torque limits is not used (the reason is returned; "" when used)."""
        if self.steps:
            return "the controller has commanded already"
        if len(effort) == 0:
            return "the driver reports no effort"
        try:
            tau, _ = self.joints.map(names, effort, effort)
            if position is not None and not self.controller.law.gravity_compensation:
                q, _ = self.joints.map(names, position, position)
                if not np.all(np.isfinite(q)):
                    return "position not finite: the gravity in the effort cannot be taken off"
                tau = tau - self.controller.arm.gravity(q)
        except JointStateError as exc:
            return f"effort not usable: {exc}"
        limits = self.controller.law.torque_limits
        if not (np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limits)):
            return f"effort not finite or beyond the torque limits: {np.round(tau, 3).tolist()}"
        self.controller.reset_rate_limit(tau.copy())
        return ""

    # ------------------------------------------------------------------ the 1 kHz step
    def on_joint_state(self, names: Sequence[str], position: Sequence[float], velocity: Sequence[float],
                       stamp_ns: int, now: float) -> tuple[np.ndarray, str]:
        """Torque (Nm, controller joint order) for one joint state received at wall time ``now`` (s).

        Returns (torque, new_fault): ``new_fault`` is the reason when this state latched a fault.
        The torque is an internal buffer: publish or copy it before the next call. ``answers(stamp)``
        says whether a state should be answered at all (``idle_mode`` "pause").

        Every state, in every mode, is checked: names and sizes, stamp order, finite values, q
        within the joint limits (+ margin) and |dq| within the velocity limits (x factor); see
        ``panda_spec``. A rejected state is counted, latches the safe hold and answers with the
        hold of the last valid state; it does not move the loop's notion of time.
        """
        self.steps += 1
        self.last_state_time = now
        ctrl = self.controller
        try:
            q, dq = self.joints.map(names, position, velocity)
        except JointStateError as exc:
            return self._reject(("names", str(exc)))
        if stamp_ns < self._last_stamp:
            return self._reject(("order", stamp_ns, self._last_stamp))
        problem = state_problem(q, dq, self.q_min, self.q_max, self.dq_max)
        if problem:
            # copies: q and dq may be views of the driver's buffers, rewritten before the text is read
            return self._reject(("value", problem, q.copy(), dq.copy()))
        self._last_stamp = stamp_ns
        had_fault = ctrl.fault
        run = self.episode
        if run is not None and stamp_ns >= self._episode_from and not had_fault:
            tau = self._episode_step(run, q, dq, stamp_ns)
        elif self.policy is None or self.config.idle_mode == "hold":
            tau = ctrl.hold(q, dq)
        else:
            tau = ctrl.step(q, dq)
        new = ""
        if ctrl.fault and not had_fault:  # the controller latched (flow not finite, ...)
            ctrl.fault = bound_text(ctrl.fault)
            self.faults += 1
            new = ctrl.fault
        self.q[:], self.dq[:] = q, dq
        self.have_state = True
        return tau, new

    def _reject(self, why: tuple) -> tuple[np.ndarray, str]:
        """Count a rejected state and keep why (as data: the text is formatted only when a fault
        latches or someone reads it, so a flood of bad states costs no string work); latch the
        hold and answer with the hold of the last valid state."""
        self.bad_inputs += 1
        self._rejection = why
        tau = self.controller.hold_last()
        if self.controller.fault:
            return tau, ""
        self._latch(self._rejection_text(why))
        return tau, self.controller.fault

    def _rejection_text(self, why: tuple) -> str:
        kind = why[0]
        if kind == "names":
            return f"bad joint state: {why[1]}"
        if kind == "order":
            return f"joint state out of order: stamp {why[1]} ns is older than the previous {why[2]} ns"
        return self._problem_text(*why[1:])

    def _problem_text(self, problem: int, q: np.ndarray, dq: np.ndarray) -> str:
        code, i = divmod(problem, PROBLEM_BASE)
        name = self.joints.joint_names[i]
        if code == Q_NOT_FINITE or code == DQ_NOT_FINITE:
            which = "position" if code == Q_NOT_FINITE else "velocity"
            bad = [self.joints.joint_names[j] for j in range(self.n)
                   if not (math.isfinite(q[j]) and math.isfinite(dq[j]))]
            return f"joint state not finite (NaN/Inf) for {bad} (first: {name} {which})"
        if code == Q_IMPLAUSIBLE:
            return (f"joint position implausible: {name} = {q[i]:.6g} rad outside [{self.q_min[i]:.4f}, "
                    f"{self.q_max[i]:.4f}] (joint limits +- {math.degrees(Q_PLAUSIBLE_MARGIN):.0f} deg)")
        if code == DQ_IMPLAUSIBLE:
            return (f"joint velocity implausible: {name} = {dq[i]:.6g} rad/s beyond +-{self.dq_max[i]:.4g} rad/s "
                    f"({DQ_PLAUSIBLE_FACTOR:g} x the velocity limit)")
        return f"joint state rejected (code {problem})"

    def _episode_step(self, run: EpisodeRun, q: np.ndarray, dq: np.ndarray, stamp_ns: int) -> np.ndarray:
        """One step of a running episode: held noise, then the record. A repeated state (a lockstep
        resend) gets the very command already sent for it: computing it again would move the torque
        rate limiter a second time and the episode would no longer be the one the sim steps."""
        ctrl = self.controller
        new = stamp_ns > self._episode_last
        if not new and not ctrl.fault:
            return self._episode_tau
        if new:
            if run.steps == 0:
                self.episode_start_ns = stamp_ns  # its samples' t count from here
                if self._episode_world_reset:
                    ctrl.reset_rate_limit()  # the sim teleported the arm: the old command acts on nothing
            self._episode_eps = run.noise()
        tau = ctrl.step(q, dq, self._episode_eps)
        if new and not ctrl.fault:
            self._episode_tau[:] = tau
            arm = ctrl.arm
            u_mean = None
            if run.steps % run.P == 0 and run.steps < run.K * run.P:
                u_mean = ctrl.evaluator.force(arm.x, ctrl.xdot, self._u_mean)
            # the effort beyond gravity: a driver that adds g(q) itself (Franka) gets a command without it
            g = arm.g if ctrl.law.gravity_compensation else self._no_gravity
            run.record(arm.x, ctrl.xdot, u_mean, self.depth, excess_norm(tau, g))
            self._episode_last = stamp_ns
        return tau

    def warm(self) -> None:
        """Before a driver waits for its next state: ``FlowController.warm`` at the last valid state,
        when the flow is what the next tick will run (an episode, or idle_mode "policy")."""
        if not self.have_state or self.controller.fault:
            return
        if self.episode is None and (self.policy is None or self.config.idle_mode != "policy"):
            return
        self.controller.warm(self.q, self.dq)

    def answers(self, stamp_ns: int) -> bool:
        """False for a state left unanswered: during a reset (``resetting``), and with idle_mode
        "pause" when no episode wants it."""
        if self.resetting:
            return False
        if self.config.idle_mode != "pause":
            return True
        return self.episode is not None and stamp_ns >= self._episode_from

    def _hold_last(self) -> np.ndarray:
        """Safe hold when the message itself is unusable: gravity of the last valid state, no damping."""
        return self.controller.hold_last()

    def on_timer(self, now: float) -> tuple[np.ndarray | None, str]:
        """Stale-state watchdog (realtime use): (hold torque to publish or None, new fault reason).

        Call it every ``state_timeout / 4`` or so. If its previous run is more than half a timeout
        ago, this process itself was starved (a stall, a swap, a busy machine): states may be
        waiting unread in its queue, so it judges nothing this time and decides on its next run.
        """
        timeout = self.config.state_timeout
        previous, self._watchdog_time = self._watchdog_time, now
        if timeout <= 0.0 or not self.have_state or now - self.last_state_time <= timeout:
            return None, ""
        if now - previous > 0.5 * timeout:
            return None, ""
        age = now - self.last_state_time
        reason = f"joint state stale: none for {age * 1e3:.1f} ms (timeout {timeout * 1e3:.1f} ms)"
        new = reason if self._latch(reason) else ""
        return self.controller.hold(self.q, np.zeros(self.n)), new

    def record_latency(self, seconds: float) -> str:
        """Account one step's latency; returns a fault reason when a run of misses latched the hold."""
        self.latency.add(seconds)
        if seconds <= self.config.deadline:
            self._consecutive_misses = 0
            return ""
        self.deadline_misses += 1
        self._consecutive_misses += 1
        limit = self.config.max_consecutive_misses
        if limit and self._consecutive_misses >= limit:
            reason = f"{self._consecutive_misses} consecutive deadline misses (> {self.config.deadline * 1e3:.2f} ms)"
            if self._latch(reason):
                return reason
        return ""

    # ------------------------------------------------------------------ energy
    def lyapunov_value(self) -> float:
        """V (J) at the last valid state, without feeding the monitor (NaN without a policy or state):
        for readers other than the one monitor caller (e.g. the action's feedback)."""
        if self.policy is None or not self.have_state:
            return float("nan")
        try:
            return float(self.controller.lyapunov(self.q, self.dq))
        except ValueError:
            return float("nan")

    def lyapunov(self, now: float | None = None) -> tuple[float, float]:
        """(V in J, filtered dV/dt in W) at the last valid state; NaN without a policy or state.

        Feeds the monitor with dt = the real time since its previous sample: ``now`` (s, any
        monotonic clock; ``time.monotonic()`` if None). Call it from one place (the status timer);
        a second call at the same ``now`` adds no sample.
        """
        if self.policy is None or not self.have_state:
            return float("nan"), float("nan")
        value = self.lyapunov_value()
        t = time.monotonic() if now is None else float(now)
        last = self._lyapunov_time
        if last is not None and not t > last:
            return value, self.monitor.rate
        self._lyapunov_time = t
        return value, self.monitor.update(value, None if last is None else t - last)
