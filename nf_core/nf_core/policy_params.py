"""Policy parameters (flow weights, noise, stiffness, damping, goal, and the law around them) with
validation.

ROS-free: ``from_msg`` reads any object with the fields of ``nf_msgs/msg/PolicyParameters``
and ``fill_msg`` writes them, so the node modules stay thin and this stays testable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .flow_spec import FlowArchitecture
from .panda_spec import MAX_REACH
from .task_spec import TaskFileError, part_from_text


class PolicyParameterError(ValueError):
    """Raised when policy parameters are malformed (wrong sizes, non-finite, not positive definite)
    or well-formed but beyond what the robot and the 1 kHz budget allow (``PolicyLimits``)."""


@dataclass(frozen=True)
class PolicyLimits:
    """The one place of the bounds a controller puts on well-formed policy parameters.

    Each bound is what the Panda and a 1 kHz step allow, with room for every setting the
    configs and docs/results use (noise 1-5 N, S up to a few hundred N/m, D up to 60 N s/m,
    weights within a few times the initialisation bound, n_flow <= 4 with n_hidden <= 32).
    """

    max_noise_std: float = 50.0  # N, exp(log_std): the Panda's TCP force is tens of N at most
    min_noise_std: float = 1e-4  # N, exp(log_std) > 0: the episode's Gaussian needs a positive std
    max_stiffness: float = 1.0e4  # N/m (latent units), largest eigenvalue of S
    max_damping: float = 1.0e3  # N s/m (latent units), largest eigenvalue of D
    max_abs_weight: float = 1.0e3  # any flow weight, dimensionless (default init bound: 1/sqrt(n_hidden))
    # Flow weights: the compiled step's time grows about linearly with them; 20,000 keeps the step well
    # inside the 1 ms period with room for the node's own work and admits n_flow 4 x n_hidden 32
    # (timings per size: docs/measurements.md, from tests/test_hostile_cost.py --sizes).
    max_flow_params: int = 20_000
    max_reach: float = MAX_REACH  # m, |x_ref| from the arm's base frame origin
    # The law around the flow (PolicyLaw): gains a 1 kHz step keeps well damped on the Panda's wrist
    max_k_rot: float = 300.0  # Nm/rad, orientation stiffness
    max_d_rot: float = 30.0  # Nm s/rad, orientation damping
    max_joint_damping: float = 10.0  # Nm s/rad, null-space joint damping


POLICY_LIMITS = PolicyLimits()
# Relative slack on the S and D bounds: a learner that clamps its gains in log space to exactly the
# bound sends exp(log(1e4)) = 10000.00000000001 (float32: 10000.001); that is the bound, not above it.
_LIMIT_RTOL = 1e-6


def _finite_array(name: str, values: Any, length: int | None = None) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if length is not None and arr.size != length:
        raise PolicyParameterError(f"{name}: expected {length} values, got {arr.size}")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise PolicyParameterError(
            f"{name}: {int(bad.sum())} non-finite value(s), first at index {int(np.argmax(bad))}"
        )
    return arr


def _spd_matrix(name: str, values: Any, dim: int) -> np.ndarray:
    mat = _finite_array(name, values, dim * dim).reshape(dim, dim)
    if not np.allclose(mat, mat.T, rtol=1e-9, atol=1e-12):
        raise PolicyParameterError(f"{name}: matrix is not symmetric: {mat.tolist()}")
    try:
        np.linalg.cholesky(mat)
    except np.linalg.LinAlgError:
        raise PolicyParameterError(
            f"{name}: matrix is not positive definite (eigenvalues {np.linalg.eigvalsh(mat).tolist()})"
        ) from None
    return mat


@dataclass(frozen=True)
class PolicyLaw:
    """What decides the torque besides the flow, S, D and x_ref: it travels with them (message and
    checkpoint), so every controller that runs a policy runs the law it was learned with."""

    potential_force_bound: float = 0.0  # N (latent space): bound on the potential's pull; 0: off
    k_rot: float = 30.0  # Nm/rad, orientation stiffness about the insertion orientation
    d_rot: float = 3.0  # Nm s/rad, orientation damping
    joint_damping: float = 0.5  # Nm s/rad, null-space joint damping
    stiffness_floor: float = 0.0  # N/m: no diagonal entry of S below it; 0: none
    held_part: str = "gear"  # the part in the hand the policy was learned with: gear | peg | none | Part.text()

    def __post_init__(self) -> None:
        for name in ("potential_force_bound", "k_rot", "d_rot", "joint_damping", "stiffness_floor"):
            try:
                value = float(getattr(self, name))
            except (TypeError, ValueError):
                value = math.nan
            if not (math.isfinite(value) and value >= 0.0):
                raise PolicyParameterError(f"law: {name} must be finite and >= 0, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        try:
            part_from_text(self.held_part)
        except TaskFileError as e:
            raise PolicyParameterError(f"law: {e}") from None

    def check_limits(self, limits: PolicyLimits = POLICY_LIMITS) -> None:
        """Raise ``PolicyParameterError`` naming the first gain beyond ``limits``."""
        for name, most, unit in (("k_rot", limits.max_k_rot, "Nm/rad"), ("d_rot", limits.max_d_rot, "Nm s/rad"),
                                 ("joint_damping", limits.max_joint_damping, "Nm s/rad")):
            if getattr(self, name) > most:
                raise PolicyParameterError(f"law: {name} {getattr(self, name):.3g} {unit}, at most {most:.3g} {unit}")

    def differences(self, other: PolicyLaw) -> list[str]:
        """``name: mine vs theirs`` for every field that differs from ``other``'s."""
        return [f"{k}: {getattr(self, k)!r} vs {getattr(other, k)!r}" for k in LAW_FIELDS
                if getattr(self, k) != getattr(other, k)]


LAW_FIELDS = tuple(PolicyLaw.__dataclass_fields__)


@dataclass
class PolicyParameters:
    """Everything the controller needs from the learner: flow weights, log-std, S, D, x_ref, the law."""

    arch: FlowArchitecture
    weights: np.ndarray  # flat flow weights, layout in flow_spec
    log_std: np.ndarray  # (1,) shared or (dim,), log of N
    stiffness: np.ndarray  # S, (dim, dim), N/m in latent units
    damping: np.ndarray  # D, (dim, dim), N s/m in latent units
    x_ref: np.ndarray  # (dim,), m, goal in the task frame
    version: int = 0
    extra: dict = field(default_factory=dict)
    law: PolicyLaw = field(default_factory=PolicyLaw)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check sizes against the architecture, finiteness and S, D positive definite; raise on error."""
        d = self.arch.dim
        self.weights = _finite_array("weights", self.weights, self.arch.n_params)
        self.log_std = _finite_array("log_std", self.log_std)
        if self.log_std.size not in (1, d):
            raise PolicyParameterError(f"log_std: expected 1 or {d} values, got {self.log_std.size}")
        self.stiffness = _spd_matrix("stiffness S", self.stiffness, d)
        self.damping = _spd_matrix("damping D", self.damping, d)
        self.x_ref = _finite_array("x_ref", self.x_ref, d)
        if self.version < 0:
            raise PolicyParameterError(f"version must be >= 0, got {self.version}")
        if not isinstance(self.law, PolicyLaw):
            raise PolicyParameterError(f"law: expected a PolicyLaw, got {type(self.law).__name__}")
        floor = self.law.stiffness_floor
        low = np.diag(self.stiffness) < floor * (1.0 - _LIMIT_RTOL)
        if floor > 0.0 and low.any():
            raise PolicyParameterError(f"stiffness S: diagonal {np.diag(self.stiffness).tolist()} N/m below the law's "
                                       f"stiffness_floor {floor:g} N/m")

    def check_limits(self, limits: PolicyLimits = POLICY_LIMITS, reach: bool = True) -> None:
        """Raise ``PolicyParameterError`` naming the first value beyond ``limits`` (the controller's
        check before it installs parameters; ``validate`` only checks that they are well-formed).
        ``reach``: also bound |x_ref| (arm tasks; the 2-D block's x_ref is not a base-frame point)."""
        n = self.arch.n_params
        if n > limits.max_flow_params:
            raise PolicyParameterError(
                f"flow too large for the 1 kHz step: {n} weights (n_flow={self.arch.n_flow}, "
                f"n_hidden={self.arch.n_hidden}), at most {limits.max_flow_params}")
        big = float(np.max(np.abs(self.weights))) if self.weights.size else 0.0
        if big > limits.max_abs_weight:
            raise PolicyParameterError(f"weights: |w| up to {big:.3g}, at most {limits.max_abs_weight:.3g}")
        lo, hi = float(np.min(self.log_std)), float(np.max(self.log_std))
        if hi > math.log(limits.max_noise_std) or lo < math.log(limits.min_noise_std):
            raise PolicyParameterError(
                f"log_std: values in [{lo:.4g}, {hi:.4g}] give a noise std outside "
                f"[{limits.min_noise_std:.3g}, {limits.max_noise_std:.3g}] N "
                f"(log_std in [{math.log(limits.min_noise_std):.3g}, {math.log(limits.max_noise_std):.3g}])")
        for name, mat, most, unit in (("stiffness S", self.stiffness, limits.max_stiffness, "N/m"),
                                      ("damping D", self.damping, limits.max_damping, "N s/m")):
            top = float(np.linalg.eigvalsh(mat)[-1])
            if top > most * (1.0 + _LIMIT_RTOL):
                raise PolicyParameterError(f"{name}: largest eigenvalue {top:.3g} {unit}, at most {most:.3g} {unit}")
        if reach:
            top = float(np.max(np.abs(self.x_ref)))  # |x| >= its largest entry; no overflow for 1e300
            dist = top if top >= limits.max_reach else float(np.linalg.norm(self.x_ref))
            if dist >= limits.max_reach:
                raise PolicyParameterError(
                    f"x_ref: {dist:.3g} m from the arm's base, beyond its reach ({limits.max_reach} m)")
        self.law.check_limits(limits)

    @classmethod
    def from_msg(cls, msg: Any) -> PolicyParameters:
        """Build and validate from an ``nf_msgs/msg/PolicyParameters`` (or any object with its fields)."""
        try:
            arch = FlowArchitecture(
                dim=int(msg.dim),
                n_flow=int(msg.n_flow),
                n_hidden=int(msg.n_hidden),
                activation=str(msg.activation),
            )
        except ValueError as exc:
            raise PolicyParameterError(f"architecture: {exc}") from None
        law = PolicyLaw(**{k: (str(v) if k == "held_part" else float(v))
                           for k, v in ((k, getattr(msg, k)) for k in LAW_FIELDS)})
        return cls(
            arch=arch,
            weights=np.asarray(msg.weights, dtype=np.float64),
            log_std=np.asarray(msg.log_std, dtype=np.float64),
            stiffness=np.asarray(msg.stiffness, dtype=np.float64),
            damping=np.asarray(msg.damping, dtype=np.float64),
            x_ref=np.asarray(msg.x_ref, dtype=np.float64),
            version=int(msg.version),
            law=law,
        )

    def fill_msg(self, msg: Any) -> Any:
        """Write these parameters into a ``nf_msgs/msg/PolicyParameters`` instance and return it."""
        msg.version = int(self.version)
        msg.dim = self.arch.dim
        msg.n_flow = self.arch.n_flow
        msg.n_hidden = self.arch.n_hidden
        msg.activation = self.arch.activation
        msg.weights = self.weights.tolist()
        msg.log_std = self.log_std.tolist()
        msg.stiffness = self.stiffness.reshape(-1).tolist()
        msg.damping = self.damping.reshape(-1).tolist()
        msg.x_ref = self.x_ref.tolist()
        for k in LAW_FIELDS:
            setattr(msg, k, getattr(self.law, k))
        return msg
