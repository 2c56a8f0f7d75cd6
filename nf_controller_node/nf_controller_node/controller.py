"""The 1 kHz controller step: joint state -> flow force -> joint torque, with safe hold on faults.

ROS-free; the node feeds it joint states and publishes what it returns. With a flow policy and
a serial-chain arm model, one ``step`` is one compiled call (state check, kinematics, joint-limit
springs, flow force, torque law): each call from Python costs a few microseconds more right after
a 1 ms wait than back to back, so a 1 kHz driver pays per call, not only per operation.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from nf_core.policy_params import PolicyLaw

from .arm_model import ArmModel
from .flow_eval import FlowEvaluator, force_kernel
from .serial_chain import chain_kinematics
from .torque_law import (
    NOT_FINITE,
    TorqueLawConfig,
    add_posture_torque,
    joint_limit_potential,
    joint_limit_torque,
    posture_potential,
    rotational_potential,
    safe_hold_torque,
    task_space_torque,
)

_Q_SANE = 2.0 * np.pi  # |q| beyond this (rad) cannot be a Panda joint angle
# |dq| beyond this (rad/s) drives no damping in the safe hold: 4x the Panda's fastest joint. The
# control loop rejects far less (panda_spec.DQ_PLAUSIBLE_MAX); this guards direct users of hold().
_DQ_SANE_HOLD = 4.0 * 2.61


@njit(cache=True)
def _state_fault(q: np.ndarray, dq: np.ndarray, q_sane: float, dq_sane: float = np.inf) -> int:
    """0 if (q, dq) is usable; 1 non-finite q, 2 non-finite dq, 3 q out of any joint range,
    4 (only if nothing else) |dq| above ``dq_sane``."""
    fast = False
    for i in range(q.shape[0]):
        if not np.isfinite(q[i]):
            return 1
        if not np.isfinite(dq[i]):
            return 2
        if abs(q[i]) > q_sane:
            return 3
        if abs(dq[i]) > dq_sane:
            fast = True
    return 4 if fast else 0


_FAULTS = {1: "joint positions not finite", 2: "joint velocities not finite", 3: "joint position out of range"}

# Codes of ``state_problem`` (code * PROBLEM_BASE + joint index).
Q_NOT_FINITE, DQ_NOT_FINITE, Q_IMPLAUSIBLE, DQ_IMPLAUSIBLE = 1, 2, 3, 4
PROBLEM_BASE = 1024


@njit(cache=True)
def state_problem(q: np.ndarray, dq: np.ndarray, q_lo: np.ndarray, q_hi: np.ndarray, dq_max: np.ndarray) -> int:
    """0 if every joint's (q, dq) is finite with q_lo <= q <= q_hi and |dq| <= dq_max; else
    code * PROBLEM_BASE + index of the first bad joint (codes Q_NOT_FINITE .. DQ_IMPLAUSIBLE).
    One compiled pass, no allocation: cheap enough for every joint state."""
    for i in range(q.shape[0]):
        if not np.isfinite(q[i]):
            return Q_NOT_FINITE * PROBLEM_BASE + i
        if not np.isfinite(dq[i]):
            return DQ_NOT_FINITE * PROBLEM_BASE + i
        if q[i] < q_lo[i] or q[i] > q_hi[i]:
            return Q_IMPLAUSIBLE * PROBLEM_BASE + i
        if abs(dq[i]) > dq_max[i]:
            return DQ_IMPLAUSIBLE * PROBLEM_BASE + i
    return 0
_FLOW_FAILED = -1


@njit(cache=True)
def _flow_step(J, R, g, x, dq, noise, wp, layout, code, consts, work, gains, R_ref, limits, tau_prev, xdot, u, tau,
               tau_joint):
    """One fused compiled call: xdot = J_v dq, u = flow force + noise, then the joint torque law.

    gains = [k_rot, d_rot, joint_damping, gravity (1/0), max torque step]. Returns the torque law's
    flags, or _FLOW_FAILED (tau untouched) when the flow's output is not finite.
    """
    n = dq.shape[0]
    for r in range(3):
        acc = 0.0
        for j in range(n):
            acc += J[r, j] * dq[j]
        xdot[r] = acc
    if force_kernel(x, xdot, wp, layout, code, consts, work, u) != 0:
        return _FLOW_FAILED
    for r in range(3):
        u[r] += noise[r]
    return task_space_torque(J, R, g, dq, u, R_ref, gains[0], gains[1], gains[2], gains[3] > 0.0,
                             tau_prev, limits, gains[4], tau, tau_joint)


_STATE_FAULT = -100  # _flow_tick: _STATE_FAULT - code for an unusable state (codes of _state_fault)


@njit(cache=True)
def _flow_tick(q, dq, noise, q_sane, joint_rot, joint_pos, axis, mass, com, tcp_rot, tcp_pos, gravity, o_rot, o_pos,
               J, x, R, g, wp, layout, code, consts, work, gains, R_ref, limits, q_lo, q_hi, q_posture, tau_prev, xdot,
               u, tau, tau_joint):
    """``FlowController.step`` for a usable state in one compiled call: state check, the arm's
    kinematics (``chain_kinematics`` into J, x, R, g), the joint-limit springs (stiffness gains[5]),
    the posture spring to ``q_posture`` (stiffness gains[8], damping gains[9]; off at 0),
    ``_flow_step``, and tau_prev = tau. Returns the torque law's flags, _FLOW_FAILED, or
    _STATE_FAULT - code when (q, dq) is unusable (nothing written)."""
    fault = _state_fault(q, dq, q_sane, np.inf)
    if fault != 0:
        return _STATE_FAULT - fault
    chain_kinematics(q, joint_rot, joint_pos, axis, mass, com, tcp_rot, tcp_pos, gravity, o_rot, o_pos, J, x, R, g)
    if gains[5] > 0.0:
        joint_limit_torque(q, q_lo, q_hi, gains[5], tau_joint)
    elif gains[8] > 0.0:
        tau_joint[:] = 0.0
    if gains[8] > 0.0:
        add_posture_torque(q, dq, q_posture, gains[8], gains[9], tau_joint)
    flags = _flow_step(J, R, g, x, dq, noise, wp, layout, code, consts, work, gains, R_ref, limits, tau_prev, xdot,
                       u, tau, tau_joint)
    if flags != _FLOW_FAILED:
        for j in range(tau.shape[0]):
            tau_prev[j] = tau[j]
    return flags


_ANCHORED_NOW = 1 << 16  # _hold_tick: set in the result when this call anchored the hold
_USABLE = 1 << 17  # _hold_tick: set when q was usable (g(q) computed into the arm's g)


@njit(cache=True)
def _hold_tick(q, dq, q_sane, dq_sane, joint_rot, joint_pos, axis, mass, com, tcp_rot, tcp_pos, gravity, o_rot,
               o_pos, J, x, R, g, g_last, dq_zero, gains, tau_prev, limits, tau, q_anchor, anchored):
    """``FlowController.hold`` for a correctly sized state in one compiled call: state check, for a
    usable q the arm's kinematics (g(q) into ``g``) and the anchor (if not ``anchored``), the hold
    law (damping gains[6], spring gains[7], gravity gains[3], rate limit gains[4]), tau_prev = tau.
    Returns the law's flags, plus _USABLE for a usable q and _ANCHORED_NOW when it anchored. An
    unusable q holds with ``g_last`` and no spring, an absurd dq (beyond ``dq_sane``) with no damping."""
    fault = _state_fault(q, dq, q_sane, dq_sane)
    bits = 0
    if fault == 0 or fault == 4:  # q usable
        bits = _USABLE
        chain_kinematics(q, joint_rot, joint_pos, axis, mass, com, tcp_rot, tcp_pos, gravity, o_rot, o_pos, J, x, R,
                         g)
        if not anchored:
            for j in range(q.shape[0]):
                q_anchor[j] = q[j]
            bits |= _ANCHORED_NOW
        flags = safe_hold_torque(g, dq if fault == 0 else dq_zero, gains[6], gains[3] > 0.0, tau_prev, limits,
                                 gains[4], tau, q, q_anchor, gains[7])
    else:
        flags = safe_hold_torque(g_last, dq_zero, gains[6], gains[3] > 0.0, tau_prev, limits, gains[4], tau,
                                 q_anchor, q_anchor, gains[7])
    for j in range(tau.shape[0]):
        tau_prev[j] = tau[j]
    return flags | bits


class FlowController:
    """Stable flow controller for the Panda. ``step(q, dq)`` returns the joint torque to command.

    On bad input it returns the safe-hold torque and latches ``fault`` until ``clear_fault()``.
    The safe hold brakes to its anchor (``hold``): the joint position of the first usable state
    it sees after anything else ran.
    The returned array is an internal buffer: copy it if you keep it. ``evaluator`` is a
    ``FlowEvaluator`` (fused compiled path) or any object with ``force(x, xdot, out)`` and
    ``potential(x)`` (e.g. a baseline MLP policy). ``law`` is read at construction and by
    ``set_law``: change gains through ``set_law``.
    """

    def __init__(self, arm: ArmModel, evaluator: FlowEvaluator, law: TorqueLawConfig | None = None) -> None:
        self.arm = arm
        n = arm.nq
        self.n = n
        self.tau = np.zeros(n)
        self.tau_prev = np.full(n, np.nan)  # NaN = no previous command: no rate limit on the first one
        self.u = np.zeros(3)  # task-space force of the flow controller (plus noise), N
        self.xdot = np.zeros(3)  # TCP velocity of the last step, m/s
        self.flags = 0
        self.fault = ""
        self._g_last = np.zeros(n)
        self._dq_zero = np.zeros(n)
        self._no_noise = np.zeros(3)
        self.tau_joint = np.zeros(n)  # joint-limit and posture springs' torque of the last step, Nm
        self.q_posture = np.zeros(n)  # joint position the posture spring pulls to (set_posture), rad
        self._posture = (0.0, 0.0)  # posture spring's stiffness (Nm/rad) and damping (Nm s/rad); 0: off
        self._q_anchor = np.zeros(n)  # joint position the safe hold's spring pulls to, rad
        self._anchored = False  # False: the next hold with a usable q anchors there
        self._scratch = [np.zeros(n), np.zeros(3), np.zeros(3), np.zeros(n), np.zeros(n)]  # warm(): outputs
        self._teleop = (0.0, 0.001)  # teleoperation: anchor speed (m/s; 0: off) and tick period (s)
        self._teleop_target: np.ndarray | None = None  # where the operator pulls the anchor, m
        self._anchor: np.ndarray | None = None  # the anchor x_ref while teleoperated; None: at the next TCP
        self.set_law(law or TorqueLawConfig())
        if not self.law.gravity_compensation:
            # The driver compensates gravity (a Franka): the arm gets no command of ours before the
            # first one, so the rate limit starts from zero; NaN would let a restarted controller's
            # first command jump past the rate limit.
            self.tau_prev[:] = 0.0
        self.set_evaluator(evaluator)

    # -- configuration --------------------------------------------------------------------
    def set_evaluator(self, evaluator: FlowEvaluator, force_bound: float | None = None) -> None:
        """Swap the flow (new policy parameters); call only between episodes. Its pull is bounded by the
        law's ``potential_force_bound``, or by ``force_bound`` N when given (a driver's reset motion)."""
        self.evaluator = evaluator
        self._anchor = None  # teleoperation: the new policy's anchor starts where the TCP is
        self._kernel_args = evaluator.kernel_args() if isinstance(evaluator, FlowEvaluator) else None
        if self._kernel_args is not None:
            evaluator.set_force_bound(self.law.potential_force_bound if force_bound is None else force_bound)

    def set_law(self, law: TorqueLawConfig) -> None:
        """Set gains and limits of the torque law; call only between episodes."""
        self.law = law
        if isinstance(getattr(self, "evaluator", None), FlowEvaluator):
            self.evaluator.set_force_bound(law.potential_force_bound)
        self.tau_joint[:] = 0.0  # recomputed each step while a joint spring is on
        self._anchored = False  # the next hold anchors where it begins, under the new law
        self._gains = np.array([law.k_rot, law.d_rot, law.joint_damping, float(law.gravity_compensation),
                                law.max_step, law.joint_limit_stiffness, law.hold_damping, law.hold_stiffness,
                                *self._posture])

    def set_policy_law(self, law: PolicyLaw) -> None:
        """Run the gains and force bound a policy carries (``PolicyLaw``); call only between episodes.
        Unlike ``set_law`` it keeps the hold's anchor: only the flow's side of the law changes."""
        new = self.law.with_policy_law(law)
        if new is self.law:
            return
        self.law = new
        self._gains[0:3] = (new.k_rot, new.d_rot, new.joint_damping)
        if isinstance(getattr(self, "evaluator", None), FlowEvaluator):
            self.evaluator.set_force_bound(new.potential_force_bound)

    def set_posture(self, q_posture: np.ndarray | None, stiffness: float = 0.0, damping: float = 0.0) -> None:
        """Add a joint spring (``stiffness``, Nm/rad) to ``q_posture`` and joint damping (``damping``,
        Nm s/rad) to the law, or remove them (``None``). The spring's energy joins V, so the law stays
        provably stable; it moves the equilibrium unless the posture is one where the task-space
        springs rest (a driver's reset motion uses the posture it reached the start in). Call only
        between steps, on the thread that steps."""
        if q_posture is None or stiffness <= 0.0:
            self._posture = (0.0, 0.0)
        else:
            q_posture = np.asarray(q_posture, dtype=np.float64)
            if q_posture.shape != (self.n,) or not np.all(np.isfinite(q_posture)):
                raise ValueError(f"posture must be {self.n} finite joint positions, got {q_posture}")
            if not (np.isfinite(stiffness) and np.isfinite(damping) and damping >= 0.0):
                raise ValueError(f"posture stiffness and damping must be finite, damping >= 0: {stiffness}, {damping}")
            self.q_posture[:] = q_posture
            self._posture = (float(stiffness), float(damping))
        self._gains[8:10] = self._posture
        self.tau_joint[:] = 0.0  # recomputed each step while a joint spring is on

    @property
    def posture(self) -> tuple[np.ndarray, float, float] | None:
        """(posture, stiffness, damping) of the posture spring, or None while it is off."""
        k, d = self._posture
        return (self.q_posture.copy(), k, d) if k > 0.0 else None

    # -- teleoperation: the operator moves the spring's anchor ------------------------------
    def set_teleop(self, speed: float, period: float = 0.001) -> None:
        """Let an operator move the law's anchor x_ref (``set_teleop_target``) at most ``speed`` m/s,
        ``period`` s per step; 0: off (x_ref is the policy's). The operator pulls a virtual spring on the
        TCP: the law stays u = -J^T S [phi(x) - phi(x_ref)] - J^T D J xdot, whose energy only the
        anchor's bounded motion can change, so the arm is as stable as under the policy. Only for a
        policy evaluated by a ``FlowEvaluator``. Call between steps."""
        if not (np.isfinite(speed) and speed >= 0.0 and np.isfinite(period) and period > 0.0):
            raise ValueError(f"teleoperation speed must be finite and >= 0 m/s, period > 0 s: {speed}, {period}")
        self._teleop = (float(speed), float(period))
        self._anchor = None

    def engage_teleop(self) -> None:
        """At an episode's start: the anchor starts at the TCP (the spring relaxed) and waits for a target."""
        self._anchor = None
        self._teleop_target = None

    def set_teleop_target(self, target: np.ndarray | None) -> None:
        """Where the operator pulls the anchor (m, task frame; None: stay). Any thread. ``ValueError``
        for a target that is not 3 finite numbers."""
        if target is not None:
            target = np.array(target, dtype=np.float64)
            if target.shape != (3,) or not np.all(np.isfinite(target)):
                raise ValueError(f"teleoperation target must be 3 finite numbers (m), got {target.tolist()}")
        self._teleop_target = target  # one reference swap: the step sees the old target or the new one

    @property
    def reference(self) -> np.ndarray | None:
        """The x_ref the law pulls to now (m; the teleoperated anchor while teleoperation is on), a copy."""
        x_ref = getattr(self.evaluator, "x_ref", None)
        return None if x_ref is None else np.array(x_ref)

    def _teleop_step(self, q: np.ndarray) -> None:
        """Move the anchor a step towards the operator's target (on the stepping thread)."""
        speed, period = self._teleop
        if not np.all(np.isfinite(q)):
            return  # the step holds on this state
        try:
            if self._anchor is None:
                self.arm.kinematics(q)  # the TCP now: the spring starts relaxed
                self._anchor = np.array(self.arm.x[:3])
                self.evaluator.move_reference(self._anchor)
            target = self._teleop_target
            if target is None:
                return
            d = target - self._anchor
            n = float(np.linalg.norm(d))
            if n == 0.0:
                return
            self._anchor += d if n <= speed * period else d * (speed * period / n)
            self.evaluator.move_reference(self._anchor)
        except ValueError as exc:  # phi not finite at the anchor: the step holds, the loop goes on
            self.fault = f"teleoperation anchor: {exc}"

    def clear_fault(self) -> None:
        """Re-arm after a fault (the caller has made sure the cause is gone). The next hold anchors
        where the arm is then: a person may have moved it, and the hold must not pull it back."""
        self.fault = ""
        self._anchored = False

    def release_hold_anchor(self) -> None:
        """Forget the safe hold's anchor: the next hold anchors at its own first usable state. For a
        driver whose arm moved without our commands (a restarted torque-control session)."""
        self._anchored = False

    @property
    def hold_anchor(self) -> np.ndarray | None:
        """Joint position (rad) the safe hold pulls to, a copy; None until a hold has anchored."""
        return self._q_anchor.copy() if self._anchored else None

    def reset_rate_limit(self, tau_now: np.ndarray | None = None) -> None:
        """Start rate limiting from ``tau_now`` (the torque the arm currently receives), or not at all."""
        self.tau_prev[:] = np.nan if tau_now is None else tau_now

    # -- the 1 kHz step -------------------------------------------------------------------
    def step(self, q: np.ndarray, dq: np.ndarray, extra_force: np.ndarray | None = None) -> np.ndarray:
        """Torque (Nm) for joint positions q (rad) and velocities dq (rad/s).

        ``extra_force`` (N, 3) is added to the flow force: the policy's exploration noise.
        """
        if q.shape != (self.n,) or dq.shape != (self.n,):
            return self._hold(q, dq, f"joint state has wrong size: q {q.shape}, dq {dq.shape}, want ({self.n},)")
        if self.fault:
            return self._hold(q, dq, self.fault)
        if self._teleop[0] > 0.0 and self._kernel_args is not None:
            self._teleop_step(q)
            if self.fault:
                return self._hold(q, dq, self.fault)
        arm, law = self.arm, self.law
        noise = self._no_noise if extra_force is None else extra_force
        if self._kernel_args is not None and arm.chain is not None:  # one compiled call
            flags = _flow_tick(q, dq, noise, _Q_SANE, *arm.chain_args, arm.J, arm.x, arm.R, arm.g, *self._kernel_args,
                               self._gains, law.rotation_ref, law.torque_limits, law.q_soft_min, law.q_soft_max,
                               self.q_posture, self.tau_prev, self.xdot, self.u, self.tau, self.tau_joint)
            if flags < _FLOW_FAILED:
                return self._hold(q, dq, _FAULTS[_STATE_FAULT - flags])
            self._anchored = False  # the flow ran: a hold after this step anchors where it begins
            self._g_last = arm.g
            if flags == _FLOW_FAILED:
                return self._hold(q, dq, f"flow force not finite at x={arm.x.tolist()}")
            self.flags = flags
            if flags & NOT_FINITE:
                self.fault = "controller produced a non-finite torque"
            return self.tau
        code = _state_fault(q, dq, _Q_SANE)
        if code:
            return self._hold(q, dq, _FAULTS[code])
        self._anchored = False  # the flow runs: a hold after this step anchors where it begins
        arm.kinematics(q)
        self._g_last = arm.g  # last valid gravity torque, kept for a hold on a bad state
        if law.joint_limit_stiffness > 0.0:
            joint_limit_torque(q, law.q_soft_min, law.q_soft_max, law.joint_limit_stiffness, self.tau_joint)
        elif self._posture[0] > 0.0:
            self.tau_joint[:] = 0.0
        if self._posture[0] > 0.0:
            add_posture_torque(q, dq, self.q_posture, *self._posture, self.tau_joint)
        if self._kernel_args is not None:
            self.flags = _flow_step(arm.J, arm.R, arm.g, arm.x, dq, noise, *self._kernel_args, self._gains,
                                    law.rotation_ref, law.torque_limits, self.tau_prev, self.xdot, self.u, self.tau,
                                    self.tau_joint)
            if self.flags == _FLOW_FAILED:
                return self._hold(q, dq, f"flow force not finite at x={arm.x.tolist()}")
        else:
            np.dot(arm.J[:3], dq, out=self.xdot)
            try:
                self.evaluator.force(arm.x, self.xdot, self.u)
            except ValueError as exc:
                return self._hold(q, dq, f"policy force failed: {exc}")
            self.u += noise
            self.flags = task_space_torque(
                arm.J, arm.R, arm.g, dq, self.u, law.rotation_ref, law.k_rot, law.d_rot, law.joint_damping,
                law.gravity_compensation, self.tau_prev, law.torque_limits, law.max_step, self.tau, self.tau_joint,
            )
        if self.flags & NOT_FINITE:
            self.fault = "controller produced a non-finite torque"
        self.tau_prev[:] = self.tau
        return self.tau

    def warm(self, q: np.ndarray, dq: np.ndarray) -> None:
        """Run the compiled part of ``step`` for (q, dq) into scratch buffers, changing nothing the
        next ``step`` reads (the arm model's cached kinematics are recomputed by every step): for a
        driver about to wait for its next state, so that the step after the wait finds the model,
        the flow's weights and the kernels' code in the caches (on this project's VM a step right
        after a 1 ms sleep takes about 4x as long as in a tight loop)."""
        args = self._kernel_args
        if args is None or self.fault:
            return
        law = self.law
        arm = self.arm
        tau_prev, xdot, u, tau, tau_joint = self._scratch
        tau_prev[:] = self.tau_prev
        tau_joint[:] = self.tau_joint
        if arm.chain is not None:  # the same compiled call as step's
            _flow_tick(q, dq, self._no_noise, _Q_SANE, *arm.chain_args, arm.J, arm.x, arm.R, arm.g, *args, self._gains,
                       law.rotation_ref, law.torque_limits, law.q_soft_min, law.q_soft_max, self.q_posture, tau_prev,
                       xdot, u, tau, tau_joint)
            return
        arm.kinematics(q)
        _flow_step(arm.J, arm.R, arm.g, arm.x, dq, self._no_noise, *args, self._gains, law.rotation_ref,
                   law.torque_limits, tau_prev, xdot, u, tau, tau_joint)

    def hold(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Safe-hold torque (no flow): gravity compensation + joint damping + a joint spring
        (``law.hold_stiffness``) to the anchor. The anchor is q of the first usable state a hold
        sees after the flow last ran (``step``), or after ``set_law``, ``clear_fault`` or
        ``release_hold_anchor``: where the fault or the idle hold began, so the arm brakes there
        instead of coasting. An unusable q holds the last valid gravity and adds no spring (a spring
        from a stale q would push open-loop; the anchor stays for the next usable state); an absurd
        dq (beyond 4x the velocity limit) drives no damping."""
        law = self.law
        arm = self.arm
        if arm.chain is not None and q.shape == dq.shape == (self.n,):  # one compiled call
            flags = _hold_tick(q, dq, _Q_SANE, _DQ_SANE_HOLD, *arm.chain_args, arm.J, arm.x, arm.R, arm.g,
                               self._g_last, self._dq_zero, self._gains, self.tau_prev, law.torque_limits, self.tau,
                               self._q_anchor, self._anchored)
            if flags & _USABLE:
                self._g_last = arm.g  # also what a Franka driver's gravity headroom reads
                if flags & _ANCHORED_NOW:
                    self._anchored = True
            self.flags = flags & ~(_USABLE | _ANCHORED_NOW)
            return self.tau
        code = _state_fault(q, dq, _Q_SANE, _DQ_SANE_HOLD) if q.shape == dq.shape == (self.n,) else 1
        q_spring = self._q_anchor  # q = anchor: no spring term
        if code == 0 or code == 4:  # q usable
            self._g_last = arm.gravity(q)  # also arm.g, which a Franka driver's gravity headroom reads
            if not self._anchored:
                self._q_anchor[:] = q
                self._anchored = True
            q_spring = q
        damp = code == 0
        self.flags = safe_hold_torque(
            self._g_last, dq if damp else self._dq_zero, law.hold_damping, law.gravity_compensation,
            self.tau_prev, law.torque_limits, law.max_step, self.tau, q_spring, self._q_anchor, law.hold_stiffness,
        )
        self.tau_prev[:] = self.tau
        return self.tau

    def hold_last(self) -> np.ndarray:
        """Safe hold on the last valid state (its gravity, no damping, no spring): for a state that
        cannot be used. The anchor stays: the spring resumes with the next usable state."""
        law = self.law
        self.flags = safe_hold_torque(self._g_last, self._dq_zero, law.hold_damping, law.gravity_compensation,
                                      self.tau_prev, law.torque_limits, law.max_step, self.tau,
                                      self._q_anchor, self._q_anchor, law.hold_stiffness)
        self.tau_prev[:] = self.tau
        return self.tau

    def _hold(self, q: np.ndarray, dq: np.ndarray, reason: str) -> np.ndarray:
        if not self.fault:
            self.fault = reason
        return self.hold(np.asarray(q, dtype=np.float64).reshape(-1), np.asarray(dq, dtype=np.float64).reshape(-1))

    # -- energy ----------------------------------------------------------------------------
    def lyapunov(self, q: np.ndarray, dq: np.ndarray) -> float:
        """V(q, dq) = flow potential + orientation spring energy + joint-limit spring energy +
        posture spring energy (while on) + kinetic energy, J."""
        arm = self.arm
        arm.update(q, dq)
        q = np.asarray(q, dtype=np.float64)
        return (
            self.evaluator.potential(arm.x)
            + rotational_potential(arm.R, self.law.rotation_ref, self.law.k_rot)
            + joint_limit_potential(q, self.law)
            + posture_potential(q, self.q_posture, self._posture[0])
            + arm.kinetic_energy(q, dq)
        )
