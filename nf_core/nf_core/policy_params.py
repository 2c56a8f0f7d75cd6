"""Policy parameters (flow weights, noise, stiffness, damping, goal) with validation.

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


@dataclass
class PolicyParameters:
    """Everything the controller needs from the learner: flow weights, log-std, S, D, x_ref."""

    arch: FlowArchitecture
    weights: np.ndarray  # flat flow weights, layout in flow_spec
    log_std: np.ndarray  # (1,) shared or (dim,), log of N
    stiffness: np.ndarray  # S, (dim, dim), N/m in latent units
    damping: np.ndarray  # D, (dim, dim), N s/m in latent units
    x_ref: np.ndarray  # (dim,), m, goal in the task frame
    version: int = 0
    extra: dict = field(default_factory=dict)

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
        return cls(
            arch=arch,
            weights=np.asarray(msg.weights, dtype=np.float64),
            log_std=np.asarray(msg.log_std, dtype=np.float64),
            stiffness=np.asarray(msg.stiffness, dtype=np.float64),
            damping=np.asarray(msg.damping, dtype=np.float64),
            x_ref=np.asarray(msg.x_ref, dtype=np.float64),
            version=int(msg.version),
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
        return msg
