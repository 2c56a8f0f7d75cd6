"""Torque law and safe hold: correct mapping, limits, and never a NaN torque."""

from __future__ import annotations

import numpy as np
import pytest

from nf_controller_node.torque_law import (
    CLAMPED,
    NOT_FINITE,
    RATE_LIMITED,
    TorqueLawConfig,
    joint_limit_potential,
    joint_limit_torque,
    orientation_error,
    rotational_potential,
    safe_hold_torque,
    task_space_torque,
)
from nf_core import panda_spec

LIMITS = panda_spec.TORQUE_LIMITS


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _law(J, R, g, dq, u, cfg, tau_prev=None):
    tau = np.zeros(7)
    prev = np.full(7, np.nan) if tau_prev is None else tau_prev
    flags = task_space_torque(J, R, g, dq, u, cfg.rotation_ref, cfg.k_rot, cfg.d_rot, cfg.joint_damping,
                              cfg.gravity_compensation, prev, cfg.torque_limits, cfg.max_step, tau, np.zeros(7))
    return tau, flags


def test_jacobian_transpose_mapping_matches_numpy():
    rng = np.random.default_rng(0)
    cfg = TorqueLawConfig()
    J, g, dq, u = rng.normal(size=(6, 7)), rng.normal(size=7), rng.normal(size=7) * 0.1, rng.normal(size=3)
    R = cfg.rotation_ref @ _rot_z(0.1)
    e = np.zeros(3)
    orientation_error(R, cfg.rotation_ref, e)
    expected = J[:3].T @ u + J[3:].T @ (cfg.k_rot * e - cfg.d_rot * (J[3:] @ dq)) - cfg.joint_damping * dq + g
    tau, flags = _law(J, R, g, dq, u, cfg)
    assert flags == 0
    np.testing.assert_allclose(tau, expected, rtol=0, atol=1e-12)
    cfg_no_g = TorqueLawConfig(gravity_compensation=False)
    tau2, _ = _law(J, R, g, dq, u, cfg_no_g)
    np.testing.assert_allclose(tau2, expected - g, atol=1e-12)


def test_orientation_error_restores_and_matches_potential_gradient():
    ref = np.eye(3)
    for axis_angle in (0.3, -0.2, 1.0):
        R = _rot_z(axis_angle)
        e = np.zeros(3)
        orientation_error(R, ref, e)
        assert e[2] == pytest.approx(-np.sin(axis_angle))  # pushes back toward the reference
        # torque k*e is minus the derivative of the spring energy along the rotation
        h = 1e-6
        dV = (rotational_potential(_rot_z(axis_angle + h), ref, 2.0)
              - rotational_potential(_rot_z(axis_angle - h), ref, 2.0)) / (2 * h)
        assert 2.0 * e[2] == pytest.approx(-dV, abs=1e-7)


def test_clamp_and_rate_limit():
    cfg = TorqueLawConfig()
    J = np.zeros((6, 7))
    J[0] = 1.0
    tau, flags = _law(J, np.eye(3) @ cfg.rotation_ref, np.zeros(7), np.zeros(7), np.array([500.0, 0, 0]), cfg)
    assert flags & CLAMPED and np.all(np.abs(tau) <= LIMITS)
    np.testing.assert_allclose(tau, LIMITS)
    prev = np.zeros(7)
    tau, flags = _law(J, cfg.rotation_ref, np.zeros(7), np.zeros(7), np.array([500.0, 0, 0]), cfg, prev)
    assert flags & RATE_LIMITED
    np.testing.assert_allclose(tau, np.full(7, cfg.max_step))  # 1000 Nm/s * 1 ms


@pytest.mark.parametrize("bad", ["J", "g", "dq", "u", "R"])
def test_non_finite_inputs_never_give_nan_torque(bad):
    rng = np.random.default_rng(1)
    cfg = TorqueLawConfig()
    args = {"J": rng.normal(size=(6, 7)), "R": cfg.rotation_ref.copy(), "g": rng.normal(size=7),
            "dq": rng.normal(size=7), "u": rng.normal(size=3)}
    args[bad].flat[0] = np.nan
    prev = rng.normal(size=7)
    tau, flags = _law(args["J"], args["R"], args["g"], args["dq"], args["u"], cfg, prev.copy())
    assert np.all(np.isfinite(tau))
    if bad != "g" or cfg.gravity_compensation:
        assert flags & NOT_FINITE
        np.testing.assert_allclose(tau, np.clip(prev, -LIMITS, LIMITS))  # holds the previous command


def test_safe_hold_drops_non_finite_terms():
    cfg = TorqueLawConfig()
    g = np.arange(7, dtype=float)
    dq = np.ones(7)
    g[2] = np.inf
    dq[4] = np.nan
    tau = np.zeros(7)
    safe_hold_torque(g, dq, cfg.hold_damping, True, np.full(7, np.nan), cfg.torque_limits, cfg.max_step, tau,
                     np.zeros(7), np.zeros(7), 0.0)
    assert np.all(np.isfinite(tau))
    assert tau[2] == -cfg.hold_damping and tau[4] == 4.0 and tau[0] == -cfg.hold_damping


@pytest.mark.parametrize("kw", [{"k_rot": -1.0}, {"dt": 0.0}, {"torque_rate_limit": float("nan")},
                                {"torque_limits": np.ones(6)}, {"rotation_ref": 2 * np.eye(3)}])
def test_bad_configuration_is_rejected(kw):
    with pytest.raises(ValueError):
        TorqueLawConfig(**kw)


def test_joint_limit_springs_push_back_only_near_a_limit_and_have_the_potential_V_uses():
    cfg = TorqueLawConfig(joint_limit_stiffness=100.0, joint_limit_margin=0.1)
    out = np.zeros(7)
    mid = 0.5 * (panda_spec.Q_MIN + panda_spec.Q_MAX)
    joint_limit_torque(mid, cfg.q_soft_min, cfg.q_soft_max, cfg.joint_limit_stiffness, out)
    assert not out.any() and joint_limit_potential(mid, cfg) == 0.0
    q = mid.copy()
    q[5] = panda_spec.Q_MAX[5] - 0.05  # 0.05 rad inside the margin of joint 6's upper limit
    q[0] = panda_spec.Q_MIN[0] + 0.02
    joint_limit_torque(q, cfg.q_soft_min, cfg.q_soft_max, cfg.joint_limit_stiffness, out)
    assert out[5] == pytest.approx(-100.0 * 0.05) and out[0] == pytest.approx(100.0 * 0.08)
    assert np.count_nonzero(out) == 2
    for i in range(7):  # the torque is minus the potential's gradient
        h = 1e-6
        up, down = q.copy(), q.copy()
        up[i] += h
        down[i] -= h
        grad = (joint_limit_potential(up, cfg) - joint_limit_potential(down, cfg)) / (2 * h)
        assert -grad == pytest.approx(out[i], abs=1e-5)
    J = np.zeros((6, 7))
    tau, _ = _law(J, np.eye(3), np.zeros(7), np.zeros(7), np.zeros(3), TorqueLawConfig(gravity_compensation=False))
    tau_k = np.zeros(7)
    task_space_torque(J, np.eye(3), np.zeros(7), np.zeros(7), np.zeros(3), cfg.rotation_ref, cfg.k_rot, cfg.d_rot,
                      cfg.joint_damping, False, np.full(7, np.nan), cfg.torque_limits, cfg.max_step, tau_k, out)
    assert tau_k - tau == pytest.approx(out), "the law adds the springs' torque"
    with pytest.raises(ValueError, match="joint limits"):
        TorqueLawConfig(joint_limit_margin=2.0)
    with pytest.raises(ValueError):
        TorqueLawConfig(joint_limit_stiffness=-1.0)
