"""The 1 kHz controller step: agrees with the pieces it is made of, and bad input never yields NaN."""

from __future__ import annotations

import math

import numpy as np
import pytest

from learner_node.flow import init_flow_weights
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.lyapunov import LyapunovMonitor
from nf_controller_node.torque_law import TorqueLawConfig, orientation_error
from nf_core import panda_spec
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameterError, PolicyParameters

ARCH = FlowArchitecture(dim=3, n_flow=2, n_hidden=16)
Q0 = np.array([0.0, -0.12, 0.0, -2.26, 0.0, 2.14, 0.785])


@pytest.fixture(scope="module")
def arm():
    return ArmModel()


def _controller(arm, seed=0):
    w = init_flow_weights(ARCH, np.random.default_rng(seed), 1.0)
    ev = FlowEvaluator(ARCH, w, 4.0 * np.eye(3), np.eye(3), np.array([0.5, 0.0, 0.1]))
    return FlowController(arm, ev)


def test_step_equals_composition_of_parts(arm):
    ctrl = _controller(arm)
    rng = np.random.default_rng(1)
    q, dq = Q0 + rng.normal(0, 0.1, 7), rng.normal(0, 0.2, 7)
    noise = np.array([0.5, -1.0, 0.25])
    tau = ctrl.step(q, dq, noise).copy()
    arm.update(q, dq)
    u = ctrl.evaluator.force(arm.x, arm.xdot) + noise
    e = np.zeros(3)
    orientation_error(arm.R, ctrl.law.rotation_ref, e)
    w = arm.J[3:] @ dq
    expected = arm.J[:3].T @ u + arm.J[3:].T @ (ctrl.law.k_rot * e - ctrl.law.d_rot * w) \
        - ctrl.law.joint_damping * dq + arm.g
    expected = np.clip(expected, -panda_spec.TORQUE_LIMITS, panda_spec.TORQUE_LIMITS)
    np.testing.assert_allclose(tau, expected, atol=1e-10)
    assert ctrl.fault == ""


def test_joint_limit_springs_join_the_step_and_V(arm):
    plain = _controller(arm)
    sprung = _controller(arm)
    sprung.set_law(TorqueLawConfig(joint_limit_stiffness=100.0, joint_limit_margin=0.1))
    q, dq = Q0.copy(), np.zeros(7)
    q[0] = panda_spec.Q_MAX[0] - 0.04  # joint 1 within 0.1 rad of its upper limit
    tau = sprung.step(q, dq).copy()
    base = plain.step(q, dq).copy()
    expected = np.zeros(7)
    expected[0] = -100.0 * 0.06
    np.testing.assert_allclose(tau - base, expected, atol=1e-9)
    assert sprung.lyapunov(q, dq) - plain.lyapunov(q, dq) == pytest.approx(0.5 * 100.0 * 0.06**2)
    sprung.reset_rate_limit()
    plain.reset_rate_limit()
    assert sprung.step(Q0, dq) == pytest.approx(plain.step(Q0, dq)), "no effect away from the limits"
    sprung.step(q, dq)  # near the limit again: the springs push
    sprung.set_law(TorqueLawConfig())  # springs off: nothing of them stays in the law
    sprung.reset_rate_limit()
    plain.reset_rate_limit()
    assert sprung.step(q, dq) == pytest.approx(plain.step(q, dq))


def test_posture_spring_joins_the_step_and_V_and_leaves_no_trace(arm):
    """The reset motion's joint spring and damping (set_posture), with and without the joint-limit
    springs, in the compiled path; off again, the step is the plain law's."""
    q_posture = Q0 + np.array([0.05, 0.0, -0.05, 0.0, 0.0, 0.0, 0.02])
    rng = np.random.default_rng(3)
    q, dq = Q0 + rng.normal(0, 0.02, 7), rng.normal(0, 0.05, 7)
    for law in (TorqueLawConfig(), TorqueLawConfig(joint_limit_stiffness=100.0)):
        plain, sprung = _controller(arm), _controller(arm)
        plain.set_law(law)
        sprung.set_law(law)
        sprung.set_posture(q_posture, 10.0, 7.0)
        assert sprung.posture is not None and sprung.posture[1:] == (10.0, 7.0)
        tau = sprung.step(q, dq).copy()
        base = plain.step(q, dq).copy()
        np.testing.assert_allclose(tau - base, 10.0 * (q_posture - q) - 7.0 * dq, atol=1e-9)
        dV = sprung.lyapunov(q, dq) - plain.lyapunov(q, dq)
        assert dV == pytest.approx(0.5 * 10.0 * float((q - q_posture) @ (q - q_posture)))
        sprung.set_posture(None)
        assert sprung.posture is None
        sprung.reset_rate_limit()
        plain.reset_rate_limit()
        np.testing.assert_allclose(sprung.step(q, dq), plain.step(q, dq), atol=1e-12)
    with pytest.raises(ValueError, match="posture must be 7"):
        sprung.set_posture(Q0[:6], 10.0, 7.0)


BAD_STATES = {
    "nan q": (np.r_[math.nan, Q0[1:]], np.zeros(7)),
    "inf dq": (Q0, np.r_[np.zeros(6), math.inf]),
    "short q": (Q0[:6], np.zeros(7)),
    "long dq": (Q0, np.zeros(8)),
    "absurd q": (Q0 + 100.0, np.zeros(7)),
}


@pytest.mark.parametrize("name", list(BAD_STATES))
def test_bad_state_gives_safe_hold_never_nan(arm, name):
    ctrl = _controller(arm)
    good = ctrl.step(Q0, np.zeros(7)).copy()
    q, dq = BAD_STATES[name]
    tau = ctrl.step(q, dq)
    assert np.all(np.isfinite(tau)), tau
    assert np.all(np.abs(tau) <= panda_spec.TORQUE_LIMITS)
    assert ctrl.fault, "fault reason must be set"
    # the hold keeps the last valid gravity compensation (no damping possible without dq)
    if name in ("nan q", "short q", "long dq", "absurd q"):
        np.testing.assert_allclose(tau, np.clip(ctrl._g_last, good - 1.0, good + 1.0), atol=1e-9)
    # latched: a good state afterwards still gets the hold until the fault is cleared
    ctrl.step(Q0, np.zeros(7))
    assert ctrl.fault
    ctrl.clear_fault()
    ctrl.step(Q0, np.zeros(7))
    assert ctrl.fault == ""


def test_random_garbage_never_produces_nan(arm):
    ctrl = _controller(arm)
    rng = np.random.default_rng(5)
    specials = np.array([math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0])
    for _ in range(500):
        q = Q0 + rng.normal(0, 1.0, 7)
        dq = rng.normal(0, 5.0, 7)
        for v in (q, dq):
            mask = rng.random(7) < 0.1
            v[mask] = rng.choice(specials, mask.sum())
        noise = rng.normal(0, 50.0, 3) if rng.random() < 0.5 else np.array([math.nan, 0.0, 0.0])
        tau = ctrl.step(q, dq, noise)
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= panda_spec.TORQUE_LIMITS)
        ctrl.clear_fault()


def test_swapped_bad_parameters_are_refused_before_use():
    good = PolicyParameters(arch=ARCH, weights=np.zeros(ARCH.n_params), log_std=np.zeros(1),
                            stiffness=np.eye(3), damping=np.eye(3), x_ref=np.zeros(3))
    with pytest.raises(PolicyParameterError, match="weights"):
        PolicyParameters(arch=ARCH, weights=np.zeros(ARCH.n_params - 1), log_std=np.zeros(1),
                         stiffness=np.eye(3), damping=np.eye(3), x_ref=np.zeros(3))
    with pytest.raises(PolicyParameterError, match="non-finite"):
        w = good.weights.copy()
        w[3] = math.nan
        PolicyParameters(arch=ARCH, weights=w, log_std=np.zeros(1), stiffness=np.eye(3),
                         damping=np.eye(3), x_ref=np.zeros(3))


def test_gravity_switch_drops_g(arm):
    ctrl = _controller(arm)
    with_g = ctrl.step(Q0, np.zeros(7)).copy()
    ctrl.set_law(TorqueLawConfig(gravity_compensation=False))
    ctrl.reset_rate_limit()
    without = ctrl.step(Q0, np.zeros(7))
    arm.update(Q0, np.zeros(7))
    np.testing.assert_allclose(with_g - without, arm.g, atol=1e-9)


def test_lyapunov_monitor_counts_rises():
    mon = LyapunovMonitor(dt=0.001, tolerance=1e-6)
    for v in (1.0, 0.9, 0.8, 0.85, 0.7):
        mon.update(v)
    assert mon.rises == 1 and mon.max_rise == pytest.approx(0.05)
    assert mon.rate < 0.0
    mon.update(math.nan)
    assert mon.rises == 2
    with pytest.raises(ValueError):
        LyapunovMonitor(dt=0.0)


def test_warm_changes_no_torque(arm):
    """``warm`` (the realtime driver's cache warm-up before it waits) runs the compiled step into
    scratch buffers: a controller warmed before every step gives bit-identical torques, rate
    limiter and fault included, to one that is never warmed."""
    plain, warmed = _controller(arm), _controller(arm)
    rng = np.random.default_rng(3)
    q, dq = Q0.copy(), np.zeros(7)
    for _ in range(50):
        warmed.warm(q + rng.normal(0, 0.05, 7), rng.normal(0, 0.5, 7))  # any state, even another one
        a = plain.step(q, dq).copy()
        b = warmed.step(q, dq).copy()
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(plain.tau_prev, warmed.tau_prev)
        np.testing.assert_array_equal(plain.xdot, warmed.xdot)
        q, dq = q + 0.001 * dq + rng.normal(0, 1e-3, 7), dq + rng.normal(0, 0.05, 7)
    warmed.fault = "latched"
    warmed.warm(q, dq)  # a latched controller is left alone
    assert warmed.fault == "latched"


def test_teleoperation_moves_the_anchor_at_most_its_speed_and_keeps_the_law(arm):
    """The operator's target pulls the anchor x_ref (from the TCP at the episode's start) at most
    ``speed`` m/s; the torque is the law's about that anchor; bad targets and states change nothing."""
    ctrl = _controller(arm)
    ctrl.set_teleop(0.1, 0.001)
    ctrl.engage_teleop()
    q, dq = Q0.copy(), np.zeros(7)
    ctrl.step(q, dq)
    tcp = arm.tcp_position(q)
    np.testing.assert_allclose(ctrl.reference, tcp, atol=1e-12)  # the spring starts relaxed at the TCP
    target = tcp + np.array([0.05, 0.0, 0.0])
    ctrl.set_teleop_target(target)
    for _ in range(100):  # 0.1 s at 0.1 m/s: 1 cm of the 5
        tau = ctrl.step(q, dq).copy()
    np.testing.assert_allclose(ctrl.reference, tcp + [0.01, 0.0, 0.0], atol=1e-12)
    # the law about the moved anchor: the same evaluator's force with x_ref there
    moved = _controller(arm)
    moved.evaluator.move_reference(ctrl.reference)
    np.testing.assert_allclose(tau, moved.step(q, dq), atol=1e-9)
    with pytest.raises(ValueError, match="3 finite"):
        ctrl.set_teleop_target(np.array([np.nan, 0.0, 0.0]))
    tau = ctrl.step(np.full(7, np.nan), dq)  # a bad state: the safe hold, the anchor stays
    assert np.all(np.isfinite(tau)) and ctrl.fault
    np.testing.assert_allclose(ctrl.reference, tcp + [0.010, 0.0, 0.0], atol=1e-3)
    ctrl.clear_fault()
    ctrl.engage_teleop()  # the next episode: from its own TCP, no target
    ctrl.step(q, dq)
    np.testing.assert_allclose(ctrl.reference, tcp, atol=1e-12)
    with pytest.raises(ValueError, match="speed"):
        ctrl.set_teleop(-1.0)

