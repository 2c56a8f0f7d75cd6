"""Task-space force to joint torque: Jacobian transpose, orientation impedance, joint damping,
gravity, torque clamp and rate limit; and the safe-hold law for faults.

The kernels are compiled with numba so one call costs about a microsecond in the 1 kHz loop.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from nf_core import panda_spec
from nf_core.policy_params import PolicyLaw

# Result flags of the torque kernels (bit mask).
CLAMPED = 1  # a joint torque hit its limit
RATE_LIMITED = 2  # a joint torque change hit the rate limit
NOT_FINITE = 4  # the law produced NaN/Inf: the output is the previous command instead
# The law's settings a policy carries (nf_core.policy_params.PolicyLaw); the rest belong to the arm.
POLICY_GAINS = ("potential_force_bound", "k_rot", "d_rot", "joint_damping")


@dataclass
class TorqueLawConfig:
    """Gains and limits of the joint torque law. Units: N m/rad, N m s/rad, N m, N m/s."""

    k_rot: float = 30.0  # orientation stiffness about the insertion orientation, Nm/rad
    d_rot: float = 3.0  # orientation damping, Nm s/rad
    joint_damping: float = 0.5  # joint-space damping for the null space, Nm s/rad
    hold_damping: float = 2.0  # joint damping of the safe-hold law, Nm s/rad
    # Joint spring of the safe hold to its anchor (the joint position where the hold began), Nm/rad.
    # 0: damping only (the arm coasts); > 0: the hold brakes the arm back to where the fault happened.
    hold_stiffness: float = 0.0
    gravity_compensation: bool = True  # False for drivers that compensate gravity themselves (Franka)
    torque_limits: np.ndarray = field(default_factory=lambda: panda_spec.TORQUE_LIMITS.copy())
    torque_rate_limit: float = panda_spec.TORQUE_RATE_LIMIT  # Nm/s
    dt: float = 0.001  # control period, s
    rotation_ref: np.ndarray = field(default_factory=lambda: panda_spec.INSERTION_ROTATION.copy())
    # Joint-limit springs: within ``joint_limit_margin`` (rad) of a joint limit (``q_min``, ``q_max``)
    # a spring of ``joint_limit_stiffness`` (Nm/rad) pushes the joint back. Conservative: its energy
    # joins V (``joint_limit_potential``), so the stability proof holds with it. 0: off.
    joint_limit_stiffness: float = 0.0
    joint_limit_margin: float = 0.1
    # Bound on the flow potential's pull, N in the latent space (FlowEvaluator.set_force_bound): beyond
    # the bound the potential grows linearly instead of quadratically, so far from x_ref a stiff policy
    # does not drive the joints into their torque limits, where the proof does not reach. Still a
    # potential: every policy stays provably stable. 0: off (the plain quadratic potential).
    potential_force_bound: float = 0.0
    q_min: np.ndarray = field(default_factory=lambda: panda_spec.Q_MIN.copy())
    q_max: np.ndarray = field(default_factory=lambda: panda_spec.Q_MAX.copy())

    def __post_init__(self) -> None:
        for name in ("k_rot", "d_rot", "joint_damping", "hold_damping", "hold_stiffness", "torque_rate_limit", "dt",
                     "joint_limit_stiffness", "joint_limit_margin", "potential_force_bound"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0.0 or (name == "dt" and value == 0.0):
                raise ValueError(f"TorqueLawConfig.{name} must be finite and >= 0 (dt > 0), got {value}")
            setattr(self, name, float(value))  # an int would compile the kernels a second time
        self.torque_limits = np.asarray(self.torque_limits, dtype=np.float64)
        if self.torque_limits.shape != (7,) or not np.all(self.torque_limits > 0):
            raise ValueError(f"torque_limits must be 7 positive values, got {self.torque_limits}")
        self.set_joint_limits(self.q_min, self.q_max)
        self.rotation_ref = np.ascontiguousarray(self.rotation_ref, dtype=np.float64)
        if self.rotation_ref.shape != (3, 3) or not np.allclose(
            self.rotation_ref @ self.rotation_ref.T, np.eye(3), atol=1e-9
        ):
            raise ValueError("rotation_ref must be a 3x3 rotation matrix")

    def set_joint_limits(self, q_min: np.ndarray, q_max: np.ndarray) -> None:
        """The arm's joint ranges (rad; a Franka driver sets the connected arm's). The springs act
        inside ``joint_limit_margin`` of them (``q_soft_min``, ``q_soft_max``)."""
        q_min = np.asarray(q_min, dtype=np.float64).copy()
        q_max = np.asarray(q_max, dtype=np.float64).copy()
        if q_min.shape != (7,) or q_max.shape != (7,) or not np.all(q_max - q_min > 2.0 * self.joint_limit_margin):
            raise ValueError(f"joint limits must be 7 ranges wider than twice the margin "
                             f"{self.joint_limit_margin} rad, got {q_min} .. {q_max}")
        self.q_min, self.q_max = q_min, q_max
        self.q_soft_min = q_min + self.joint_limit_margin
        self.q_soft_max = q_max - self.joint_limit_margin

    def with_policy_law(self, law: PolicyLaw) -> TorqueLawConfig:
        """This law with a policy's gains and force bound (``POLICY_GAINS`` of a ``PolicyLaw``); itself
        if they are already its own."""
        if all(getattr(self, k) == getattr(law, k) for k in POLICY_GAINS):
            return self
        return dataclasses.replace(self, **{k: float(getattr(law, k)) for k in POLICY_GAINS})

    @property
    def max_step(self) -> float:
        """Largest torque change per control period, Nm."""
        return self.torque_rate_limit * self.dt


@njit(cache=True)
def excess_norm(tau: np.ndarray, g: np.ndarray) -> float:
    """|tau - g| (Nm): the torque beyond gravity compensation, the episodes' effort measure."""
    acc = 0.0
    for i in range(tau.shape[0]):
        d = tau[i] - g[i]
        acc += d * d
    return np.sqrt(acc)


@njit(cache=True)
def orientation_error(R: np.ndarray, R_ref: np.ndarray, out: np.ndarray) -> None:
    """out = 1/2 sum_i r_i x r_ref_i: the axis-angle-like error (world frame) that turns R toward R_ref."""
    out[:] = 0.0
    for i in range(3):
        a0, a1, a2 = R[0, i], R[1, i], R[2, i]
        b0, b1, b2 = R_ref[0, i], R_ref[1, i], R_ref[2, i]
        out[0] += 0.5 * (a1 * b2 - a2 * b1)
        out[1] += 0.5 * (a2 * b0 - a0 * b2)
        out[2] += 0.5 * (a0 * b1 - a1 * b0)


@njit(cache=True)
def _limit(tau: np.ndarray, tau_prev: np.ndarray, limits: np.ndarray, max_step: float) -> int:
    flags = 0
    for i in range(tau.shape[0]):
        v = tau[i]
        if max_step > 0.0 and np.isfinite(tau_prev[i]):
            if v > tau_prev[i] + max_step:
                v = tau_prev[i] + max_step
                flags |= RATE_LIMITED
            elif v < tau_prev[i] - max_step:
                v = tau_prev[i] - max_step
                flags |= RATE_LIMITED
        if v > limits[i]:
            v = limits[i]
            flags |= CLAMPED
        elif v < -limits[i]:
            v = -limits[i]
            flags |= CLAMPED
        tau[i] = v
    return flags


@njit(cache=True)
def _fallback(tau: np.ndarray, tau_prev: np.ndarray) -> None:
    for i in range(tau.shape[0]):
        tau[i] = tau_prev[i] if np.isfinite(tau_prev[i]) else 0.0


@njit(cache=True)
def joint_limit_torque(q: np.ndarray, q_lo: np.ndarray, q_hi: np.ndarray, k: float, out: np.ndarray) -> None:
    """out = the joint-limit springs' torque: k (q_lo - q) below q_lo, k (q_hi - q) above q_hi, else 0."""
    for i in range(q.shape[0]):
        v = 0.0
        if q[i] < q_lo[i]:
            v = k * (q_lo[i] - q[i])
        elif q[i] > q_hi[i]:
            v = k * (q_hi[i] - q[i])
        out[i] = v


@njit(cache=True)
def add_posture_torque(q: np.ndarray, dq: np.ndarray, q_posture: np.ndarray, stiffness: float, damping: float,
                       out: np.ndarray) -> None:
    """out += stiffness (q_posture - q) - damping dq: a joint spring to a posture and its damping.
    The spring is conservative (energy ``posture_potential``), the damping dissipates."""
    for i in range(q.shape[0]):
        out[i] += stiffness * (q_posture[i] - q[i]) - damping * dq[i]


def posture_potential(q: np.ndarray, q_posture: np.ndarray, stiffness: float) -> float:
    """Energy (J) of the posture spring of ``add_posture_torque``."""
    d = np.asarray(q, dtype=np.float64) - q_posture
    return 0.5 * stiffness * float(d @ d)


def joint_limit_potential(q: np.ndarray, law: TorqueLawConfig) -> float:
    """Energy (J) of the joint-limit springs whose torque is ``joint_limit_torque``."""
    below = np.minimum(q - law.q_soft_min, 0.0)
    above = np.maximum(q - law.q_soft_max, 0.0)
    return 0.5 * law.joint_limit_stiffness * float(below @ below + above @ above)


@njit(cache=True)
def task_space_torque(
    J: np.ndarray, R: np.ndarray, g: np.ndarray, dq: np.ndarray, u: np.ndarray, R_ref: np.ndarray,
    k_rot: float, d_rot: float, joint_damping: float, use_gravity: bool,
    tau_prev: np.ndarray, limits: np.ndarray, max_step: float, tau: np.ndarray, tau_joint: np.ndarray,
) -> int:
    """tau = J_v^T u + J_w^T (k_rot e_R - d_rot w) - joint_damping dq + tau_joint (+ g), then rate
    limit and clamp. ``tau_joint``: joint-space torque of conservative terms (joint-limit springs).

    Writes ``tau`` and returns the flag mask. Never writes NaN: on a non-finite result ``tau``
    becomes the previous command (or zero) and NOT_FINITE is returned.
    """
    n = tau.shape[0]
    e = np.empty(3)
    orientation_error(R, R_ref, e)
    w = np.zeros(3)
    for r in range(3):
        for j in range(n):
            w[r] += J[3 + r, j] * dq[j]
    m0 = k_rot * e[0] - d_rot * w[0]
    m1 = k_rot * e[1] - d_rot * w[1]
    m2 = k_rot * e[2] - d_rot * w[2]
    finite = True
    for j in range(n):
        v = (J[0, j] * u[0] + J[1, j] * u[1] + J[2, j] * u[2]
             + J[3, j] * m0 + J[4, j] * m1 + J[5, j] * m2 - joint_damping * dq[j] + tau_joint[j])
        if use_gravity:
            v += g[j]
        if not np.isfinite(v):
            finite = False
        tau[j] = v
    if not finite:
        _fallback(tau, tau_prev)
        return NOT_FINITE | _limit(tau, tau_prev, limits, max_step)
    return _limit(tau, tau_prev, limits, max_step)


@njit(cache=True)
def safe_hold_torque(
    g: np.ndarray, dq: np.ndarray, damping: float, use_gravity: bool,
    tau_prev: np.ndarray, limits: np.ndarray, max_step: float, tau: np.ndarray,
    q: np.ndarray, q_anchor: np.ndarray, stiffness: float,
) -> int:
    """Safe hold: tau = g(q) - damping * dq - stiffness * (q - q_anchor) (g omitted when the driver
    compensates), rate-limited, clamped. ``q = q_anchor`` (or stiffness 0) gives no spring.

    Non-finite g, dq or spring terms are dropped term by term, so the hold never outputs NaN.
    """
    for j in range(tau.shape[0]):
        v = 0.0
        if use_gravity and np.isfinite(g[j]):
            v += g[j]
        if np.isfinite(dq[j]):
            v -= damping * dq[j]
        if stiffness > 0.0:
            spring = stiffness * (q[j] - q_anchor[j])
            if np.isfinite(spring):
                v -= spring
        tau[j] = v
    return _limit(tau, tau_prev, limits, max_step)


def rotational_potential(R: np.ndarray, R_ref: np.ndarray, k_rot: float) -> float:
    """Energy of the orientation spring whose torque is k_rot * orientation_error: k/2 (3 - tr(R_ref^T R)), J."""
    return 0.5 * k_rot * (3.0 - float(np.sum(R_ref * R)))
