"""Issue 14, "hold means stop": the safe hold brakes the arm to where the hold began (its anchor)
instead of letting it coast. Unit tests of the anchor rule, then the braking on the simulated arm."""

from __future__ import annotations

import math
import time
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest
import yaml

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.torque_law import TorqueLawConfig, safe_hold_torque
from nf_core import panda_spec
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters
from sim_bridge_node.env import InsertionEnv

Q0 = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])  # the gear scene's start
DELTA = np.array([0.02, -0.01, 0.015, 0.01, -0.02, 0.01, 0.03])  # rad, a small displacement
K, D = 50.0, 4.0  # Nm/rad, Nm s/rad: the unit tests' hold
NAMES = list(panda_spec.JOINT_NAMES)
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel()


def _gravity(arm: ArmModel, q: np.ndarray) -> np.ndarray:
    return pin.computeGeneralizedGravity(arm.model, arm.data, q).copy()


def _flow() -> FlowEvaluator:
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=4, activation="gelu")
    params = PolicyParameters(arch, np.zeros(arch.n_params), np.zeros(1), np.eye(3), np.eye(3),
                              np.array([0.5, 0.0, 0.3]))
    return FlowEvaluator.from_params(params)


def _hold_ctrl(arm: ArmModel, k: float = K, d: float = D, evaluator=None) -> FlowController:
    law = TorqueLawConfig(hold_stiffness=k, hold_damping=d)
    return FlowController(arm, evaluator if evaluator is not None else _flow(), law)


def _hold(ctrl: FlowController, q: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
    """One hold without the rate limit (the tests compare the law's value)."""
    ctrl.reset_rate_limit()
    return ctrl.hold(np.asarray(q, dtype=float), np.zeros(7) if dq is None else dq).copy()


# ---------------------------------------------------------------------------- the law
def test_hold_spring_points_back_to_the_anchor(arm):
    ctrl = _hold_ctrl(arm)
    assert ctrl.hold_anchor is None
    np.testing.assert_allclose(_hold(ctrl, Q0), _gravity(arm, Q0), atol=1e-9)  # at the anchor: no spring
    np.testing.assert_array_equal(ctrl.hold_anchor, Q0)
    q, dq = Q0 + DELTA, np.full(7, 0.1)
    tau = _hold(ctrl, q, dq)
    np.testing.assert_allclose(tau, _gravity(arm, q) - D * dq - K * DELTA, atol=1e-9)
    np.testing.assert_array_equal(ctrl.hold_anchor, Q0)  # the first hold state, not the latest
    assert np.all(np.sign(tau - _gravity(arm, q) + D * dq) == -np.sign(DELTA))


def test_zero_stiffness_is_the_old_hold_exactly(arm):
    ctrl = _hold_ctrl(arm, k=0.0, d=2.0)
    assert TorqueLawConfig().hold_stiffness == 0.0
    _hold(ctrl, Q0)
    q, dq = Q0 + DELTA, np.full(7, 0.3)
    # to rounding: the controller's g(q) is the compiled serial chain's, _gravity is Pinocchio's
    np.testing.assert_allclose(_hold(ctrl, q, dq), _gravity(arm, q) - 2.0 * dq, rtol=0, atol=1e-12)


@pytest.mark.parametrize("value", [-1.0, math.nan, math.inf])
def test_bad_hold_stiffness_is_refused(value):
    with pytest.raises(ValueError, match="hold_stiffness"):
        TorqueLawConfig(hold_stiffness=value)


def test_node_parameter_reaches_the_law_and_is_checked(arm):
    from nf_controller_node import node

    p = {name: value for name, (value, _) in node.PARAMETERS.items()}
    assert p["hold_stiffness"] == 0.0 and "anchor" in node.PARAMETERS["hold_stiffness"][1]
    p["hold_stiffness"] = 80.0
    assert node._loop_from(p, arm).controller.law.hold_stiffness == 80.0
    p["hold_stiffness"] = -1.0
    with pytest.raises(ValueError, match="hold_stiffness"):
        node._loop_from(p, arm)


def test_flow_step_invalidates_the_anchor_a_faulted_step_does_not(arm):
    ctrl = _hold_ctrl(arm)
    _hold(ctrl, Q0)
    ctrl.step(Q0 + 0.5 * DELTA, np.zeros(7))  # the flow ran: normal control resumed
    assert ctrl.hold_anchor is None
    q1 = Q0 + DELTA
    np.testing.assert_allclose(_hold(ctrl, q1), _gravity(arm, q1), atol=1e-9)  # anchored here: no spring
    np.testing.assert_array_equal(ctrl.hold_anchor, q1)
    # a step that only holds (latched fault) keeps the anchor: the hold goes on braking to q1
    ctrl.fault = "test fault"
    ctrl.reset_rate_limit()
    tau = ctrl.step(Q0, np.zeros(7)).copy()
    np.testing.assert_array_equal(ctrl.hold_anchor, q1)
    np.testing.assert_allclose(tau, _gravity(arm, Q0) + K * DELTA, atol=1e-9)
    ctrl.clear_fault()
    assert ctrl.hold_anchor is None


def test_set_law_and_release_drop_the_anchor(arm):
    ctrl = _hold_ctrl(arm)
    _hold(ctrl, Q0)
    ctrl.set_law(TorqueLawConfig(hold_stiffness=K, hold_damping=D))
    assert ctrl.hold_anchor is None
    _hold(ctrl, Q0)
    ctrl.release_hold_anchor()
    assert ctrl.hold_anchor is None


def test_unusable_states_keep_the_anchor_add_no_spring_and_never_nan(arm):
    ctrl = _hold_ctrl(arm)
    q1 = Q0 + DELTA
    nan_q = np.r_[math.nan, q1[1:]]
    tau = _hold(ctrl, nan_q)  # the very first hold sees a bad q: nothing to anchor to
    assert np.all(np.isfinite(tau)) and ctrl.hold_anchor is None
    _hold(ctrl, Q0)
    _hold(ctrl, q1)  # last valid state: away from the anchor, gravity g(q1)
    g1 = _gravity(arm, q1)
    for bad in (nan_q, np.r_[q1[:6], math.inf], Q0 + 100.0, Q0[:6]):
        tau = _hold(ctrl, bad, np.zeros(bad.shape))
        assert np.all(np.isfinite(tau)), bad
        np.testing.assert_allclose(tau, g1, atol=1e-9)  # last gravity, no spring from a bad q
        np.testing.assert_array_equal(ctrl.hold_anchor, Q0)
    ctrl.reset_rate_limit()
    np.testing.assert_allclose(ctrl.hold_last(), g1, atol=1e-9)
    np.testing.assert_allclose(_hold(ctrl, q1), g1 - K * DELTA, atol=1e-9)  # the spring resumes
    rng = np.random.default_rng(3)
    specials = np.array([math.nan, math.inf, -math.inf, 1e308, -1e308])
    for _ in range(300):
        q, dq = Q0 + rng.normal(0, 1.0, 7), rng.normal(0, 3.0, 7)
        for v in (q, dq):
            mask = rng.random(7) < 0.15
            v[mask] = rng.choice(specials, mask.sum())
        tau = ctrl.hold(q, dq) if rng.random() < 0.8 else ctrl.hold_last()
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= panda_spec.TORQUE_LIMITS)
        if rng.random() < 0.05:
            ctrl.release_hold_anchor()


def test_kernel_drops_a_non_finite_spring_term():
    cfg = TorqueLawConfig()
    q = np.full(7, 0.1)
    anchor = np.zeros(7)
    q[2], anchor[4] = math.nan, math.inf
    tau = np.zeros(7)
    safe_hold_torque(np.zeros(7), np.zeros(7), 0.0, True, np.full(7, np.nan), cfg.torque_limits, cfg.max_step,
                     tau, q, anchor, 10.0)
    expected = np.full(7, -1.0)
    expected[2] = expected[4] = 0.0
    np.testing.assert_allclose(tau, expected, atol=1e-12)


def test_clear_fault_reanchors_where_the_arm_is(arm):
    """A person moved the arm while it was held: after clear_fault the hold must not pull it back."""
    loop = ControlLoop(arm, TorqueLawConfig(hold_stiffness=K, hold_damping=D), LoopConfig(idle_mode="hold"))
    ctrl = loop.controller
    stamp = [1_000_000]

    def feed(q: np.ndarray) -> np.ndarray:
        stamp[0] += 1_000_000
        ctrl.reset_rate_limit()
        tau, _ = loop.on_joint_state(NAMES, q, np.zeros(7), stamp[0], 0.0)
        return tau.copy()

    feed(Q0)  # no policy yet: the loop holds, anchored here
    np.testing.assert_array_equal(ctrl.hold_anchor, Q0)
    feed(np.r_[math.nan, Q0[1:]])  # a bad state latches a fault
    assert loop.fault.startswith("joint state not finite")
    moved = Q0 + 5.0 * DELTA  # meanwhile a person moves the arm: the latched hold resists
    np.testing.assert_allclose(feed(moved), _gravity(arm, moved) - 5.0 * K * DELTA, atol=1e-9)
    assert loop.clear_fault()
    np.testing.assert_allclose(feed(moved), _gravity(arm, moved), atol=1e-9)  # anchored at the new place
    np.testing.assert_array_equal(ctrl.hold_anchor, moved)


# ---------------------------------------------------------------------------- physics
BRAKE_SECONDS = 1.0
DQ_FAULT = np.array([0.5, -0.3, 0.4, 0.4, -0.5, 0.5, 0.6])  # rad/s at the fault: TCP ~0.6 m/s


def _franka_hold() -> tuple[float, float]:
    """hold_stiffness, hold_damping of config/franka.yaml (the values a real arm brakes with)."""
    section = yaml.safe_load((REPO / "config" / "franka.yaml").read_text())["/**/nf_controller"]["ros__parameters"]
    return float(section["hold_stiffness"]), float(section["hold_damping"])


def _brake(env: InsertionEnv, arm: ArmModel, k: float, d: float) -> dict:
    """The arm moving at DQ_FAULT from the gear start, then only the safe hold (gravity compensated)
    for BRAKE_SECONDS; the rate limit starts from the gravity torque the arm was getting."""
    env.reset()
    env.data.qvel[:7] = DQ_FAULT
    mujoco.mj_forward(env.model, env.data)
    ctrl = FlowController(arm, _flow(), TorqueLawConfig(hold_stiffness=k, hold_damping=d))
    ctrl.reset_rate_limit(env.bias_torques)
    q0 = env.q
    x0 = arm.tcp_position(q0)
    speed0 = float(np.linalg.norm(env.xdot))
    worst = 0.0
    for _ in range(int(round(BRAKE_SECONDS / env.model.opt.timestep))):
        tau = ctrl.hold(env.q, env.dq)
        assert np.all(np.isfinite(tau))
        env.step(tau)
        worst = max(worst, float(np.linalg.norm(env.x - x0)))
    np.testing.assert_array_equal(ctrl.hold_anchor, q0)
    return {"speed0": speed0, "max_mm": 1e3 * worst, "final_mm": 1e3 * float(np.linalg.norm(env.x - x0)),
            "final_rad": float(np.max(np.abs(env.q - q0))), "speed": float(np.linalg.norm(env.xdot))}


def test_braking_hold_stops_the_simulated_arm_where_the_fault_happened(arm):
    """MuJoCo Panda (free scene, gear in the hand) moving at ~0.6 m/s when the hold takes over."""
    env = InsertionEnv("free")
    assert np.allclose(env.q, Q0)
    k, d = _franka_hold()
    assert k > 0.0
    t = time.perf_counter()
    coast = _brake(env, arm, 0.0, TorqueLawConfig().hold_damping)
    brake = _brake(env, arm, k, d)
    print(f"\nsafe hold from {coast['speed0']:.2f} m/s TCP speed, {BRAKE_SECONDS:g} s simulated: "
          f"damping only (hold_stiffness 0, hold_damping {TorqueLawConfig().hold_damping:g}) coasts "
          f"{coast['final_mm']:.0f} mm and still moves at {coast['speed']:.2f} m/s; braking hold (franka.yaml: "
          f"hold_stiffness {k:g}, hold_damping {d:g}) goes at most {brake['max_mm']:.0f} mm and ends "
          f"{brake['final_mm']:.1f} mm ({brake['final_rad']:.4f} rad) from where the hold began "
          f"[{time.perf_counter() - t:.1f} s wall]")
    assert coast["final_mm"] > 200.0 and coast["speed"] > 0.1, coast  # the old hold lets the arm coast
    assert brake["final_mm"] < 5.0 and brake["final_rad"] < 0.01, brake
    assert brake["max_mm"] < 0.2 * coast["final_mm"], (brake, coast)
