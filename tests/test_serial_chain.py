"""The compiled serial-chain kinematics equal Pinocchio's, and the controller's fused step (one
compiled call) equals its step through Pinocchio and separate kernels."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from franka_driver.robot_model import FR3, PANDA
from learner_node.flow import init_flow_weights
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.serial_chain import SerialChain, chain_kinematics
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.flow_spec import FlowArchitecture

Q0 = np.array([0.0, -0.12, 0.0, -2.26, 0.0, 2.14, 0.785])


def _pinocchio(model, frame_id: int, q: np.ndarray) -> tuple[np.ndarray, ...]:
    data = model.createData()
    pin.computeJointJacobians(model, data, q)
    oMf = pin.updateFramePlacement(model, data, frame_id)
    J = pin.getFrameJacobian(model, data, frame_id, pin.LOCAL_WORLD_ALIGNED)
    g = pin.computeGeneralizedGravity(model, data, q)
    return J.copy(), oMf.translation.copy(), oMf.rotation.copy(), g.copy()


def _compiled(chain: SerialChain, q: np.ndarray) -> tuple[np.ndarray, ...]:
    n = q.shape[0]
    J, x, R, g = np.full((6, n), np.nan), np.full(3, np.nan), np.full((3, 3), np.nan), np.full(n, np.nan)
    chain_kinematics(q, *chain.args, J, x, R, g)
    return J, x, R, g


ARMS = {
    "panda with gear": lambda: ArmModel(),
    "panda empty hand": lambda: ArmModel(part=None),
    "fr3 with gear": lambda: FR3.arm_model(panda_spec.GEAR_PART),
    "panda spec, no armature": lambda: PANDA.arm_model(None, armature=np.zeros(7)),
}


@pytest.mark.parametrize("name", list(ARMS))
def test_compiled_kinematics_equal_pinocchio(name):
    arm = ARMS[name]()
    assert arm.chain is not None
    rng = np.random.default_rng(0)
    for _ in range(100):
        q = rng.uniform(-3.0, 3.0, 7)
        ours = _compiled(arm.chain, q)
        theirs = _pinocchio(arm.model, arm.tcp_id, q)
        for what, a, b in zip(("J", "x", "R", "g"), ours, theirs, strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()), err_msg=what)


def _unaligned_chain() -> tuple[pin.Model, int]:
    """Three revolute joints about tilted axes, with masses: a chain no Panda has."""
    model = pin.Model()
    parent = 0
    rng = np.random.default_rng(5)
    for i in range(3):
        axis = rng.normal(size=3)
        placement = pin.SE3(pin.rpy.rpyToMatrix(*rng.uniform(-1, 1, 3)), rng.uniform(-0.3, 0.3, 3))
        parent = model.addJoint(parent, pin.JointModelRevoluteUnaligned(axis / np.linalg.norm(axis)), placement,
                                f"j{i}")
        model.appendBodyToJoint(parent, pin.Inertia(1.0 + i, rng.uniform(-0.1, 0.1, 3), np.eye(3) * 0.01),
                                pin.SE3.Identity())
    frame = model.addFrame(pin.Frame("tip", parent, 0, pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.1])),
                                     pin.FrameType.OP_FRAME))
    return model, frame


def test_unaligned_revolute_axes_equal_pinocchio():
    model, frame = _unaligned_chain()
    chain = SerialChain.from_pinocchio(model, frame)
    assert chain is not None
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.uniform(-3.0, 3.0, 3)
        for a, b in zip(_compiled(chain, q), _pinocchio(model, frame, q), strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_models_that_are_not_serial_revolute_chains_are_left_to_pinocchio():
    slider = pin.Model()
    joint = slider.addJoint(0, pin.JointModelPX(), pin.SE3.Identity(), "slide")
    frame = slider.addFrame(pin.Frame("tip", joint, 0, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    assert SerialChain.from_pinocchio(slider, frame) is None
    branched = pin.Model()
    a = branched.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "a")
    branched.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "b")  # a second child of the base
    frame = branched.addFrame(pin.Frame("tip", a, 0, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    assert SerialChain.from_pinocchio(branched, frame) is None
    panda = ArmModel()
    hand = panda.model.getFrameId(panda_spec.HAND_FRAME)
    assert SerialChain.from_pinocchio(panda.model, hand) is not None
    link3 = next(i for i, f in enumerate(panda.model.frames) if f.parentJoint == 3)
    assert SerialChain.from_pinocchio(panda.model, link3) is None  # not on the last joint


def _pair(law: TorqueLawConfig) -> tuple[FlowController, FlowController]:
    arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16)
    controllers = []
    for fused in (True, False):
        arm = ArmModel()
        if not fused:
            arm.chain, arm.chain_args = None, ()  # Pinocchio and the separate kernels
        w = init_flow_weights(arch, np.random.default_rng(0), 1.0)
        ev = FlowEvaluator(arch, w, 4.0 * np.eye(3), np.eye(3), np.array([0.5, 0.0, 0.1]))
        controllers.append(FlowController(arm, ev, law))
    return controllers[0], controllers[1]


@pytest.mark.parametrize("springs", [False, True], ids=["plain", "joint_limit_springs"])
def test_fused_step_equals_the_step_through_pinocchio(springs):
    law = TorqueLawConfig(joint_limit_stiffness=100.0, joint_limit_margin=0.3) if springs else TorqueLawConfig()
    fused, plain = _pair(law)
    rng = np.random.default_rng(2)
    q, dq = Q0.copy(), np.zeros(7)
    for k in range(300):
        noise = rng.normal(0.0, 30.0, 3) if k % 3 else None  # large: clamps and the rate limit act
        a, b = fused.step(q, dq, noise).copy(), plain.step(q, dq, noise).copy()
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
        assert fused.flags == plain.flags and fused.fault == plain.fault == ""
        for name in ("tau_prev", "xdot", "u", "tau_joint"):
            np.testing.assert_allclose(getattr(fused, name), getattr(plain, name), rtol=0, atol=1e-10, err_msg=name)
        np.testing.assert_allclose(fused.arm.g, plain.arm.g, rtol=0, atol=1e-10)
        q = np.clip(q + rng.normal(0.0, 0.05, 7), panda_spec.Q_MIN, panda_spec.Q_MAX)
        dq = rng.normal(0.0, 0.5, 7)
    assert springs == bool(np.any(fused.tau_joint))


@pytest.mark.parametrize("bad", ["nan q", "inf dq", "absurd q"])
def test_fused_step_holds_on_a_bad_state_as_the_plain_step_does(bad):
    fused, plain = _pair(TorqueLawConfig())
    for ctrl in (fused, plain):
        ctrl.step(Q0, np.zeros(7))
    q, dq = Q0.copy(), np.zeros(7)
    if bad == "nan q":
        q[2] = math.nan
    elif bad == "inf dq":
        dq[6] = math.inf
    else:
        q[1] = 100.0
    a, b = fused.step(q, dq).copy(), plain.step(q, dq).copy()
    assert fused.fault == plain.fault != ""
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    assert np.all(np.isfinite(a))


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "pinocchio"])
def test_the_arm_gravity_follows_the_hold_too(fused):
    """A Franka driver clamps each command to limit - |g(q)| from ``arm.g``: in hold mode (no flow
    step) it must still be the gravity of the latest usable state, not of the last flow step."""
    ctrl = _pair(TorqueLawConfig(gravity_compensation=False))[0 if fused else 1]
    q1, q2 = Q0.copy(), Q0 + np.array([0.3, 0.4, -0.2, 0.3, 0.5, -0.4, 0.2])
    ctrl.step(q1, np.zeros(7))
    ctrl.hold(q2, np.zeros(7))
    expected = _pinocchio(ctrl.arm.model, ctrl.arm.tcp_id, q2)[3]
    np.testing.assert_allclose(ctrl.arm.g, expected, rtol=0, atol=1e-10)
    bad = q2.copy()
    bad[0] = math.nan
    ctrl.hold(bad, np.zeros(7))  # an unusable state keeps the last valid gravity
    np.testing.assert_allclose(ctrl.arm.g, expected, rtol=0, atol=1e-10)


def test_fused_hold_equals_the_hold_through_pinocchio():
    """The safe hold in one compiled call: the same torques, flags, anchor and last valid gravity as
    the hold through Pinocchio and separate kernels, over usable states, NaN and absurd positions
    (last gravity, no spring), absurd velocities (no damping), wrong sizes, and re-anchoring."""
    law = TorqueLawConfig(gravity_compensation=True, hold_stiffness=80.0, hold_damping=10.0)
    fused, plain = _pair(law)
    rng = np.random.default_rng(4)
    q = Q0.copy()
    for k in range(400):
        dq = rng.normal(0.0, 0.5, 7)
        q_in, dq_in = q.copy(), dq.copy()
        if k % 17 == 5:
            q_in[3] = math.nan
        elif k % 23 == 7:
            q_in[0] = 100.0
        elif k % 19 == 3:
            dq_in[2] = 50.0  # beyond 4x the velocity limit: no damping
        elif k % 29 == 11:
            q_in = q_in[:6]
        if k % 31 == 0:
            fused.release_hold_anchor()
            plain.release_hold_anchor()
        a, b = fused.hold(q_in, dq_in).copy(), plain.hold(q_in, dq_in).copy()
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10, err_msg=str(k))
        assert np.all(np.isfinite(a))
        assert fused.flags == plain.flags and fused._anchored == plain._anchored, k
        if plain.hold_anchor is not None:
            np.testing.assert_array_equal(fused.hold_anchor, plain.hold_anchor)
        np.testing.assert_allclose(fused._g_last, plain._g_last, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fused.tau_prev, plain.tau_prev, rtol=0, atol=1e-10)
        q = np.clip(q + rng.normal(0.0, 0.02, 7), panda_spec.Q_MIN, panda_spec.Q_MAX)
