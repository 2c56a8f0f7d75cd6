"""Pinocchio arm model: TCP, Jacobian and gravity are consistent with each other and with the URDF."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from nf_controller_node.arm_model import ArmModel
from nf_core import panda_spec


@pytest.fixture(scope="module")
def arm():
    return ArmModel()


def _random_q(rng):
    return rng.uniform(panda_spec.Q_MIN, panda_spec.Q_MAX)


def test_joint_order_and_dimensions(arm):
    assert arm.nq == 7
    assert [arm.model.names[i] for i in range(1, 8)] == list(panda_spec.JOINT_NAMES)
    np.testing.assert_allclose(arm.model.armature, panda_spec.JOINT_ARMATURE)


def test_tcp_jacobian_matches_finite_differences(arm):
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = _random_q(rng)
        arm.update(q, np.zeros(7))
        J = arm.J.copy()
        h = 1e-7
        for j in range(7):
            dq = np.zeros(7)
            dq[j] = h
            dx = (arm.tcp_position(q + dq) - arm.tcp_position(q - dq)) / (2 * h)
            np.testing.assert_allclose(J[:3, j], dx, atol=1e-7)


def test_gravity_is_gradient_of_potential_energy(arm):
    rng = np.random.default_rng(1)
    q = _random_q(rng)
    arm.update(q, np.zeros(7))
    h = 1e-6
    grad = np.zeros(7)
    for j in range(7):
        e = np.zeros(7)
        e[j] = h
        grad[j] = (pin.computePotentialEnergy(arm.model, arm.data, q + e)
                   - pin.computePotentialEnergy(arm.model, arm.data, q - e)) / (2 * h)
    np.testing.assert_allclose(arm.g, grad, atol=1e-6)


def test_gear_mass_is_carried(arm):
    bare = ArmModel(part=None)
    total = sum(i.mass for i in arm.model.inertias)
    assert total - sum(i.mass for i in bare.model.inertias) == pytest.approx(panda_spec.GEAR_MASS)


def test_tcp_points_down_at_home(arm):
    q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    arm.update(q, np.zeros(7))
    np.testing.assert_allclose(arm.R, panda_spec.INSERTION_ROTATION, atol=2e-3)
    pin.framesForwardKinematics(arm.model, arm.data, q)
    hand = arm.data.oMf[arm.model.getFrameId("panda_hand")]
    np.testing.assert_allclose(arm.x - hand.translation, hand.rotation @ panda_spec.TCP_IN_HAND, atol=1e-12)
