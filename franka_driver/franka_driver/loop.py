"""libfranka's 1 kHz torque loop hosting the flow controller (``ControllerHost``). ROS-free.

The robot's side of ``nf_core.driver_loop.DriverLoop`` (which owns the thread, its priority, the
tick's order and timing, and the episode hand-over). Per tick, on the driver thread::

    host.service()                    # posted work (policy swaps, episode starts) in the slack
    state, _ = control.readOnce()     # blocks until the robot's next state
    tau = host.tick(stamp, q, dq)     # the controller: always finite (flow or safe hold)
    control.writeOnce(Torques(tau))   # the robot adds its own gravity torque
    ... after the write: task depth from kinematics, reset progress, timing

Nothing slow happens between ``readOnce`` returning and ``writeOnce``. ``TickTiming`` measures
that latency, the loop period and the cycles the robot reports as missed.

Episodes (``begin_episode``) start with a reset *motion*: the stable controller itself (identity
flow, ``reset_stiffness``/``reset_damping``) drives the TCP to ``start_position``; when it is there
and still (``reset_tolerance``, ``reset_speed``, ``reset_settle`` ticks; the posture below within
``reset_posture_tolerance``) the episode starts from
the next state, with the torque rate limit in force. The reset's pull is bounded to
``reset_force_bound`` whatever the episode policy's law says. A reset that does not converge within
``reset_timeout`` (robot time) fails the episode and the arm is held. The task-space law leaves the
arm's self-motion to joint damping, so episodes can turn the posture while the TCP stays put; the
reset motion therefore also pulls the joints to a posture (``reset_posture``, by default where the
first reset reached the start) with a joint spring, so that every episode starts from the same
posture and the drift cannot build up over a long run.
Where a straight pull would run into the cell (a clamp between the fixture and the start), the reset
motion passes through ``reset_via`` first, one spring at a time: each point counts as passed within
``reset_via_tolerance``; the joint spring acts on the last leg only.

libfranka's exceptions (reflexes, network) end torque control: the running episode is aborted,
the error is kept for /diagnostics, and the loop waits. Without ``automatic_error_recovery`` the
controller's safe hold is latched too and only a person restarts (``request_recovery()``, then the
controller's clear_fault). With it, the loop recovers after ``recovery_wait`` and goes on; an
episode asked for meanwhile starts its reset motion once torque control is back.

Hand-guiding (``guide``): every episode, after its reset motion, commands zero torque, so the robot's
own gravity compensation is all the arm gets and a person moves it (teaching by demonstration; the
episode's states are recorded as any other's). The command ramps from the reset's to zero at the
torque rate limit. The guide stops the episode (aborted, with the reason) and hands the arm to the
safe hold when a joint moves faster than ``guide_joint_speed``, comes within ``guide_limit_margin`` of
a limit, or the episode runs longer than ``guide_timeout``. However the guide ends, the hold anchors
where the arm is and its command starts from zero.
"""

from __future__ import annotations

import gc
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.host import ControllerHost
from nf_core.driver_loop import DriverLoop
from nf_core.episode import EpisodeRun
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters
from nf_core.tick_timing import TickTiming

GRAVITY_MARGIN = 0.5  # Nm kept free below a joint's limit on top of the robot's gravity torque


@dataclass
class DriverConfig:
    """Settings of the driver loop. Units: m, s, N/m, N s/m."""

    start_position: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.0, 0.35]))  # TCP, base frame
    reset_timeout: float = 20.0  # s of robot time a reset motion may take
    reset_tolerance: float = 0.002  # m from start_position
    reset_speed: float = 0.005  # m/s, TCP speed below which the arm counts as still
    reset_settle: int = 200  # ticks in a row within tolerance and still
    reset_stiffness: float = 1500.0  # N/m of the reset motion's spring (stiff: joint friction stops a soft
    reset_damping: float = 100.0  # N s/m   spring short by friction / stiffness)
    # N: the reset motion's pull is bounded to this (0: no bound), whatever the episode policy's law says:
    # a long way at reset_stiffness would otherwise pull with hundreds of N, up to the torque limits
    reset_force_bound: float = 60.0
    # The reset motion's joint spring (Nm/rad) and damping (Nm s/rad) to reset_posture (rad; None: the
    # joints where the first reset reached the start). A conservative potential: the reset stays stable.
    reset_posture_stiffness: float = 20.0
    reset_posture_damping: float = 10.0
    reset_posture: np.ndarray | None = None
    reset_posture_tolerance: float = 0.1  # rad, largest joint's distance to it that counts as arrived
    reset_via: np.ndarray | None = None  # (k, 3) m: TCP points a reset passes through before start_position
    reset_via_tolerance: float = 0.02  # m from a via point that counts as passed
    fixture_position: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.0, 0.07]))  # mouth, base frame
    fixture_radius: float = 0.005  # m: laterally within this of the fixture axis counts as "inside"
    success_depth: float = 0.016  # m below the mouth
    automatic_error_recovery: bool = False  # restart after a libfranka error without a person
    recovery_wait: float = 1.0  # s before an automatic recovery
    goal: np.ndarray | None = None  # m: the x_ref an episode's policy must have (None: any)
    goal_tolerance: float = 0.001  # m
    gravity_headroom: bool = True  # clamp each command to limit - |g(q)| (the robot adds g on top)
    keep_timing: bool = False  # keep every latency and period (benchmark)
    guide: bool = False  # hand-guiding: episodes command zero torque (module docstring)
    guide_joint_speed: float = 1.0  # rad/s: a joint faster than this stops the guide into the hold
    guide_limit_margin: float = 0.05  # rad: a joint this close to a limit stops the guide into the hold
    guide_timeout: float = 60.0  # s of robot time a guided episode may last

    @property
    def posture_spring(self) -> bool:
        """Whether reset motions pull the joints to a posture."""
        return self.reset_posture_stiffness > 0.0

    def check(self) -> None:
        """Raise ``ValueError`` naming the first bad value."""
        for name in ("start_position", "fixture_position"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be 3 finite values (m), got {getattr(self, name)}")
            setattr(self, name, v)
        for name in ("reset_timeout", "reset_tolerance", "reset_speed", "reset_stiffness", "reset_damping",
                     "reset_posture_tolerance", "fixture_radius", "success_depth", "recovery_wait",
                     "guide_joint_speed", "guide_limit_margin", "guide_timeout", "reset_via_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be > 0, got {value}")
        for name in ("reset_posture_stiffness", "reset_posture_damping", "reset_force_bound"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {value}")
        if self.reset_posture is not None:
            posture = np.asarray(self.reset_posture, dtype=float)
            if posture.ndim != 1 or not np.all(np.isfinite(posture)):
                raise ValueError(f"reset_posture must be finite joint positions (rad), got {self.reset_posture}")
            self.reset_posture = posture
        if self.reset_via is not None:
            via = np.asarray(self.reset_via, dtype=float)
            if via.ndim != 2 or via.shape[1] != 3 or not len(via) or not np.all(np.isfinite(via)):
                raise ValueError(f"reset_via must be finite TCP points (m), 3 values each, got {self.reset_via}")
            self.reset_via = via
        if self.goal is not None:
            goal = np.asarray(self.goal, dtype=float)
            if goal.shape != (3,) or not np.all(np.isfinite(goal)):
                raise ValueError(f"goal must be 3 finite values (m) or empty, got {self.goal}")
            self.goal = goal
        if self.reset_settle < 1:
            raise ValueError(f"reset_settle must be >= 1, got {self.reset_settle}")


def reset_policy(start: np.ndarray, stiffness: float, damping: float) -> PolicyParameters:
    """The reset motion's policy: identity flow (all weights zero), S = stiffness I, D = damping I,
    x_ref = ``start``. Stable like every policy of the controller."""
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=4, activation="gelu")
    return PolicyParameters(arch, np.zeros(arch.n_params), np.zeros(1), stiffness * np.eye(3),
                            damping * np.eye(3), np.asarray(start, dtype=float).copy())


class _Reset:
    """A reset motion in progress (driver thread only)."""

    def __init__(self, run: EpisodeRun, future: Future, deadline_ns: int, evaluator: FlowEvaluator,
                 via: list[tuple[np.ndarray, FlowEvaluator]] | None = None) -> None:
        self.run = run
        self.future = future
        self.deadline_ns = deadline_ns  # robot time
        self.via = list(via or [])  # (point, its spring's evaluator) still to pass, in order
        self.final = evaluator  # the spring to the start
        self.evaluator = self.via[0][1] if self.via else evaluator  # the spring pulling now
        self.saved_evaluator: Any = None
        self.saved_idle = ""
        self.settled = 0
        self.error = math.inf  # m, last distance to the start
        self.posture: np.ndarray | None = None  # joints its posture spring pulls to (None: no spring)


class FrankaDriverLoop(DriverLoop):
    """libfranka's side of ``nf_core.driver_loop.DriverLoop`` around a ``ControllerHost``: read,
    write, the work after the write, reset motions, sessions and error recovery; see the module
    docstring.

    ``robot``: a ``pylibfranka.Robot`` (or anything with ``start_torque_control``, ``read_once``,
    ``stop``, ``automatic_error_recovery``); ``tcp(q)``: the TCP position (m) for joint positions.
    ``after_tick(q, dq, tau, stamp_ns)`` runs after each write, ``tau`` the command written (keep it to a
    few microseconds).
    ``rt_priority``: the loop thread's SCHED_FIFO priority when ``start`` runs it (0: normal).
    """

    def __init__(self, robot: Any, host: ControllerHost, tcp: Callable[[np.ndarray], np.ndarray],
                 config: DriverConfig, torque_factory: Callable[[list[float]], Any],
                 exceptions: tuple[type[BaseException], ...] = (RuntimeError,),
                 after_tick: Callable[[np.ndarray, np.ndarray, np.ndarray, int], None] | None = None,
                 connect: Callable[[], Any] | None = None, rt_priority: int = 0) -> None:
        config.check()
        if config.reset_posture is not None and config.reset_posture.shape != (host.loop.n,):
            raise ValueError(f"reset_posture must be {host.loop.n} joint positions (rad), got {config.reset_posture}")
        # a robot needs a command every cycle: every state is ticked, also while the controller idles
        super().__init__(host, TickTiming(config.keep_timing), rt_priority, label="torque loop thread",
                         thread_name="franka-driver", answer_every_state=True)
        self.host: ControllerHost = host
        self.robot = robot
        self.connect = connect  # a new connection when the old one is broken (libfranka's network errors)
        self.tcp = tcp
        self.config = config
        self.torques = torque_factory
        self.franka_errors = exceptions
        self.after_tick = after_tick
        self.law = host.loop.controller.law
        self.base_limits = self.law.torque_limits.copy()
        self.exceptions = 0  # libfranka exceptions caught
        self.last_error = ""  # text of the latest one ("" while none)
        self.recoveries = 0
        self.sessions = 0  # torque-control sessions started
        self.in_error = False
        self.depth = float("nan")
        self.success = False
        self.x = np.full(3, np.nan)  # TCP at the last state
        self._reset: _Reset | None = None
        self._stamp_offset = 0  # ns added to the robot's clock: a new connection may start it at zero
        self._recover = threading.Event()
        self._deferred: tuple[Callable[[], None], Future] | None = None  # a reset waiting for a recovery
        self.resets_done = 0
        self.resets_failed = 0
        self.last_reset = ""  # outcome of the latest reset, for diagnostics
        # the reset motion's posture (rad): configured, or where the first reset reached the start
        self.posture = None if config.reset_posture is None else config.reset_posture.copy()
        # the current session's (driver thread): libfranka's motion handle, the last state read
        self._control: Any = None
        self._rebase = False
        self._duration: Any = None
        self._q = self._dq = np.zeros(host.loop.n)
        self._stamp_ns = 0
        self._arm = host.loop.controller.arm
        # hand-guiding (driver thread): whether this tick guides, the first stamp of the guide, the last command
        self._guiding = False
        self._guide_since_ns = 0
        self._zero = np.zeros(host.loop.n)
        self._sent = np.zeros(host.loop.n)  # Nm, the last command written (without the robot's gravity)
        self._guide_step = self.law.torque_rate_limit * self.law.dt  # Nm per tick towards zero
        self.guides = 0  # guided episodes begun
        self.guide_stops = 0  # guides stopped by a limit
        self.last_guide_stop = ""

    # ------------------------------------------------------------------ episodes (DriverLoop.begin_episode)
    def reset(self, seed: int, run: EpisodeRun, done: Future) -> Callable[[], None]:
        """Move to ``start_position`` with the stable controller, then start ``run`` (``seed`` is
        unused: a robot starts where the reset motion brings it); ``done`` is completed when the
        episode runs, or holds why the reset failed."""
        c = self.config
        # the slow part, on the caller's thread
        evaluator = self.host.loop.prepare_policy(reset_policy(c.start_position, c.reset_stiffness, c.reset_damping))
        via = [(p, self.host.loop.prepare_policy(reset_policy(p, c.reset_stiffness, c.reset_damping)))
               for p in (c.reset_via if c.reset_via is not None else [])]

        def start_reset() -> None:
            loop = self.host.loop
            if self.in_error and self.config.automatic_error_recovery:
                self._deferred = (start_reset, done)  # runs again when torque control is back
                return
            if self.in_error:
                raise RuntimeError(f"libfranka error, torque control stopped: {self.last_error}")
            if loop.policy is None:
                raise RuntimeError("no policy installed")
            if loop.fault:
                raise RuntimeError(f"safe hold: {loop.fault}")
            goal = self.config.goal
            if goal is not None and np.linalg.norm(loop.policy.x_ref - goal) > self.config.goal_tolerance:
                raise RuntimeError(f"the policy's x_ref {loop.policy.x_ref.tolist()} is not the goal parameter "
                                   f"{goal.tolist()} (tolerance {self.config.goal_tolerance * 1e3:g} mm): publish "
                                   "it with deploy_policy --x-ref, or change the goal")
            if self._reset is not None:
                raise RuntimeError("a reset is already running")
            deadline = self.host.last_stamp_ns + int(self.config.reset_timeout * 1e9)
            reset = _Reset(run, done, deadline, evaluator, via)
            ctrl = loop.controller
            reset.saved_evaluator, reset.saved_idle = ctrl.evaluator, loop.config.idle_mode
            ctrl.set_evaluator(reset.evaluator, self.config.reset_force_bound)
            if not reset.via:
                self._posture_spring(reset)
            loop.config.idle_mode = "policy"
            self._reset = reset

        return start_reset

    def _posture_spring(self, reset: _Reset) -> None:
        """The reset's joint spring to the posture (not on the first reset: no posture yet)."""
        if self.posture is not None and self.config.posture_spring:
            reset.posture = self.posture.copy()
            self.host.loop.controller.set_posture(reset.posture, self.config.reset_posture_stiffness,
                                                  self.config.reset_posture_damping)

    def _end_reset(self, problem: str) -> None:
        """Driver thread: restore the controller's policy; start the episode or fail the future."""
        reset, self._reset = self._reset, None
        if reset is None:
            return
        loop = self.host.loop
        ctrl = loop.controller
        if ctrl.evaluator is reset.evaluator:
            ctrl.set_evaluator(reset.saved_evaluator)
        ctrl.set_posture(None)  # the episode's law has no posture term
        loop.config.idle_mode = reset.saved_idle
        if not problem and reset.future.cancelled():
            problem = "canceled"
        if not problem:
            try:
                self.host.start_episode(reset.run, self.host.last_stamp_ns + 1, world_was_reset=False)
            except ValueError as exc:
                problem = str(exc)
        if not problem and self.posture is None:
            self.posture = self._q.copy()  # the posture every later reset returns to
        posture = "" if self.posture is None else f", posture {np.abs(self._q - self.posture).max():.3f} rad off"
        self.last_reset = (problem or f"reached the start ({reset.error * 1e3:.2f} mm)") + posture
        if problem:
            self.resets_failed += 1
            if not reset.future.done():
                reset.future.set_exception(RuntimeError(f"reset motion: {problem}"))
        else:
            self.resets_done += 1
            if not reset.future.done():
                reset.future.set_result(None)

    def _reset_progress(self, x: np.ndarray, stamp_ns: int) -> None:
        reset = self._reset
        loop = self.host.loop
        ctrl = loop.controller
        if ctrl.evaluator is not reset.evaluator:  # a policy arrived and was installed meanwhile
            reset.saved_evaluator = ctrl.evaluator
            ctrl.set_evaluator(reset.evaluator, self.config.reset_force_bound)
        elif reset.evaluator.force_bound != self.config.reset_force_bound:  # a new law set its bound
            reset.evaluator.set_force_bound(self.config.reset_force_bound)
        if loop.fault:
            self._end_reset(f"safe hold: {loop.fault}")
            return
        if reset.future.cancelled():
            self._end_reset("canceled")
            return
        if reset.via:  # a via point: on to the next spring once it is passed
            if np.linalg.norm(x - reset.via[0][0]) < self.config.reset_via_tolerance:
                reset.via.pop(0)
                reset.evaluator = reset.via[0][1] if reset.via else reset.final
                ctrl.set_evaluator(reset.evaluator, self.config.reset_force_bound)
                if not reset.via:
                    self._posture_spring(reset)
        reset.error = float(np.linalg.norm(x - self.config.start_position))
        speed = float(np.linalg.norm(ctrl.xdot))
        posture = reset.posture is None or np.abs(self._q - reset.posture).max() < self.config.reset_posture_tolerance
        if reset.error < self.config.reset_tolerance and speed < self.config.reset_speed and posture:
            reset.settled += 1
            if reset.settled >= self.config.reset_settle:
                self._end_reset("")
                return
        else:
            reset.settled = 0
        if stamp_ns > reset.deadline_ns:
            self._end_reset(f"not at the start after {self.config.reset_timeout:.1f} s of robot time "
                            f"({reset.error * 1e3:.1f} mm away, TCP speed {speed * 1e3:.1f} mm/s)")

    # ------------------------------------------------------------------ task from kinematics
    def task_of(self, x: np.ndarray) -> tuple[float, bool]:
        """(insertion depth in m, success) of a TCP at ``x`` relative to the fixture mouth."""
        c = self.config
        f = c.fixture_position
        if math.hypot(x[0] - f[0], x[1] - f[1]) >= c.fixture_radius:
            return 0.0, False
        depth = max(float(f[2] - x[2]), 0.0)
        return depth, depth >= c.success_depth

    # ------------------------------------------------------------------ the loop
    def request_recovery(self) -> None:
        """A person cleared the robot's error (e.g. via the ~/recover service): restart control."""
        self._recover.set()

    def run(self, stop: threading.Event) -> None:
        """Torque control until ``stop`` is set (call on the driver thread). A libfranka error ends
        a session; see the module docstring for what follows."""
        while not stop.is_set():
            failed = False
            try:
                self._session(stop)
            except Exception as exc:  # libfranka's (and anything else): the loop must not die
                self._on_franka_error(exc)
                failed = True
            # outside the except block: the exception's traceback (and libfranka's motion handle in
            # it) is gone before a recovery reconnects
            if failed and not self._wait_for_recovery(stop):
                return

    def _session(self, stop: threading.Event) -> None:
        self._control = self.robot.start_torque_control()
        try:
            self._open_session()
            self.ticks(stop)
            # stop asked: finish the motion cleanly with a zero command
            try:
                self._control.readOnce()
                last = self.torques([0.0] * self.host.loop.n)
                last.motion_finished = True
                self._control.writeOnce(last)
            except self.franka_errors:
                pass
        finally:
            self._control = None  # libfranka's motion handle goes with the session

    def _open_session(self) -> None:
        loop = self.host.loop
        ctrl = loop.controller
        self.sessions += 1
        self.in_error = False
        self.timing.restart()
        ctrl.reset_rate_limit(np.zeros(loop.n))  # the robot gets no torque from us before the first write
        self._sent[:] = 0.0
        self._guiding = False
        ctrl.release_hold_anchor()  # the arm may have moved since the last session (a reflex, a person)
        self._rebase = True  # first state of this session: keep the stamps increasing across reconnects
        deferred, self._deferred = self._deferred, None
        if deferred is not None:
            start, future = deferred
            try:
                start()
            except Exception as exc:  # the episode's future says why
                if not future.done():
                    future.set_exception(exc)

    # ------------------------------------------------------------------ the hardware side (DriverLoop.ticks)
    def read(self) -> tuple[int, np.ndarray, np.ndarray, float]:
        """libfranka's next state (blocks until it comes); the tick counts from its arrival."""
        state, self._duration = self._control.readOnce()
        read = time.perf_counter()
        q = np.array(state.q)
        dq = np.array(state.dq)
        stamp_ns = int(state.time.to_sec() * 1e9 + 0.5) + self._stamp_offset
        if self._rebase:
            self._rebase = False
            last = self.host.last_stamp_ns
            if stamp_ns <= last:
                self._stamp_offset += last + 1_000_000 - stamp_ns
                stamp_ns = last + 1_000_000
        self._q, self._dq, self._stamp_ns = q, dq, stamp_ns
        return stamp_ns, q, dq, read

    def write(self, tau: np.ndarray) -> None:
        """The command; the robot adds its own gravity torque. While hand-guiding, zero torque instead."""
        if self.config.guide and (self._guiding or (self._reset is None and self.host.loop.episode is not None)):
            tau = self._guide_command()
        self._sent[:] = tau
        self._control.writeOnce(self.torques(tau.tolist()))

    def guide_problem(self, q: np.ndarray, dq: np.ndarray, elapsed_s: float) -> str:
        """Why a guide must stop at joints ``q`` (rad), ``dq`` (rad/s) after ``elapsed_s`` s ("" while it may go on)."""
        c = self.config
        law = self.host.loop.controller.law  # the arm's joint limits
        fast = np.abs(dq)
        j = int(np.argmax(fast))
        if not fast[j] <= c.guide_joint_speed:  # NaN stops it too
            return f"joint {j + 1} at {fast[j]:.2f} rad/s (guide_joint_speed {c.guide_joint_speed:g})"
        room = np.minimum(q - law.q_min, law.q_max - q)
        j = int(np.argmin(room))
        if not room[j] >= c.guide_limit_margin:
            return (f"joint {j + 1} at {q[j]:.3f} rad, {max(room[j], 0.0):.3f} rad from its limit "
                    f"(guide_limit_margin {c.guide_limit_margin:g})")
        if elapsed_s > c.guide_timeout:
            return f"guided for {elapsed_s:.1f} s (guide_timeout {c.guide_timeout:g})"
        return ""

    def _guide_command(self) -> np.ndarray:
        """Driver thread, hand-guiding: the command ramped towards zero while the episode runs and no limit is
        reached; on leaving (the episode ended, or a limit stopped it), the hold anchors here from zero."""
        loop = self.host.loop
        if loop.episode is not None and self._reset is None:
            if not self._guiding:
                self._guiding = True
                self._guide_since_ns = self._stamp_ns
                self.guides += 1
            problem = self.guide_problem(self._q, self._dq, (self._stamp_ns - self._guide_since_ns) * 1e-9)
            if not problem:
                return self._sent - np.clip(self._sent, -self._guide_step, self._guide_step)
            self.guide_stops += 1
            self.last_guide_stop = problem
            self.host.end_episode(f"aborted: hand-guiding stopped: {problem}")
        self._guiding = False
        ctrl = loop.controller
        ctrl.reset_rate_limit(self._sent)  # the hold's first command ramps from what the arm gets now
        ctrl.release_hold_anchor()  # and holds where the person left the arm
        return self._sent

    def update(self) -> None:
        """After the write (the next state is ~1 ms away): missed cycles, the gravity headroom of the
        next command, the TCP, the task, the reset motion's progress, ``after_tick``."""
        robot_dt = self._duration.to_sec()
        if robot_dt > 0.0015:  # the robot's time since the previous read spans more than one cycle
            self.timing.missed_cycles += int(round(robot_dt / 0.001)) - 1
        q, stamp_ns = self._q, self._stamp_ns
        if self.config.gravity_headroom:  # the robot adds g(q) to our command: keep |command + g| within the limit
            law_limits = self.law.torque_limits
            np.subtract(self.base_limits, np.abs(self._arm.g), out=law_limits)
            np.maximum(law_limits, GRAVITY_MARGIN, out=law_limits)
            law_limits -= GRAVITY_MARGIN
        x = self.tcp(q)
        self.x = x
        self.depth, self.success = self.task_of(x)
        self.host.set_task(self.depth, self.success)
        if self._reset is not None:
            self._reset_progress(x, stamp_ns)
        if self.after_tick is not None:
            self.after_tick(q, self._dq, self._sent, stamp_ns)  # the command written (zero while guided)

    def _on_franka_error(self, exc: BaseException) -> None:
        """A reflex or a lost connection: torque control has ended. Abort, latch the hold, keep why."""
        self.exceptions += 1
        text = f"{type(exc).__name__}: {exc}"
        try:
            errors = self.robot.read_once().last_motion_errors
            if errors:
                text += f" (last motion errors: {errors})"
        except Exception:  # the robot may be gone (pylibfranka then raises a plain RuntimeError)
            pass
        self.last_error = text[:500]
        loop = self.host.loop
        if self._reset is not None:
            self._end_reset(f"libfranka error: {self.last_error}")
        if loop.episode is not None:
            self.host.end_episode(f"aborted: libfranka error: {self.last_error}")
        if not self.config.automatic_error_recovery and not loop.controller.fault:
            # hold after the restart until a person clears it (automatic recovery goes on by itself)
            loop.controller.fault = f"libfranka error: {self.last_error}"[:300]
            loop.faults += 1
        self.in_error = True  # last: whoever sees it sees the rest done

    def _wait_for_recovery(self, stop: threading.Event) -> bool:
        """After an error: recover automatically (when configured) or wait for ``request_recovery``.
        Posted work is still served meanwhile. False when ``stop`` was set."""
        deadline = time.monotonic() + self.config.recovery_wait
        while not stop.is_set():
            self.host.service()
            if self.config.automatic_error_recovery and time.monotonic() >= deadline:
                break
            if self._recover.wait(0.05):
                break
        if stop.is_set():
            return False
        self._recover.clear()
        try:
            self.robot.stop()  # no motion may be left open on the robot's side
        except Exception:
            pass
        try:
            self.robot.automatic_error_recovery()
            self.recoveries += 1
            return True
        except Exception as exc:  # after a network error libfranka's connection is unusable
            problem = f"{type(exc).__name__}: {exc}"
        if self.connect is None:
            self.exceptions += 1
            self.last_error = f"recovery failed: {problem}"[:500]
            return True
        self.robot = None  # close the broken connection first: the robot serves one client
        gc.collect()
        try:
            self.robot = self.connect()
            self.robot.automatic_error_recovery()
            self.recoveries += 1
        except Exception as exc:  # still gone: the next session fails again and we wait again
            self.exceptions += 1
            self.last_error = f"reconnect failed: {type(exc).__name__}: {exc}"[:500]
        return True

