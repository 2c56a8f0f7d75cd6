"""The controller's Pinocchio arm model and the MuJoCo Panda, built from the same URDF, agree.

Gravity torques, mass matrix (with rotor armature) and the TCP Jacobian and pose of the held
part, for the gear and the peg, at random configurations, to 1e-9.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from nf_controller_node.arm_model import ArmModel
from nf_core import panda_spec
from nf_core.task_spec import held_part_inertia
from sim_bridge_node.held_parts import GEAR, PEG
from sim_bridge_node.scenes import build_scene

TOL = 1e-9
PARTS = {"free": GEAR, "peg": PEG}  # the free scene holds the gear


@pytest.fixture(scope="module", params=list(PARTS))
def pair(request):
    """(scene name, held part, controller arm model, MuJoCo model, MuJoCo data)."""
    part = PARTS[request.param]
    model = build_scene(request.param).model
    return request.param, part, ArmModel(part=part), model, mujoco.MjData(model)


@pytest.fixture(scope="module")
def mujoco_arm():
    model = build_scene("free").model
    return model, mujoco.MjData(model)


def _random_configurations(n: int, seed: int = 7) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(panda_spec.Q_MIN, panda_spec.Q_MAX, size=(n, 7))


def test_model_shape(pair):
    _, _, _, model, _ = pair
    assert model.nq == model.nv == model.nu == 7
    assert [model.joint(i).name for i in range(model.njnt)] == list(panda_spec.JOINT_NAMES)
    np.testing.assert_array_equal(model.actuator_ctrlrange[:, 1], panda_spec.TORQUE_LIMITS)
    np.testing.assert_array_equal(model.actuator_ctrlrange[:, 0], -panda_spec.TORQUE_LIMITS)
    np.testing.assert_array_equal(model.dof_armature, panda_spec.JOINT_ARMATURE)
    np.testing.assert_array_equal(model.dof_damping, panda_spec.JOINT_DAMPING)
    assert model.opt.timestep == 0.001


def test_gravity_mass_matrix_and_jacobian_agree(pair):
    _, part, arm, model, data = pair
    site = model.site(part.tcp_site).id
    jacp, jacr = np.zeros((3, 7)), np.zeros((3, 7))
    mj_mass = np.zeros((7, 7))
    for q in _random_configurations(20):
        data.qpos[:] = q
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)
        arm.update(q, np.zeros(7))
        np.testing.assert_allclose(arm.g, data.qfrc_bias, rtol=0, atol=TOL)
        mujoco.mj_fullM(model, data, mj_mass)
        np.testing.assert_allclose(arm.mass_matrix(q), mj_mass, rtol=0, atol=TOL)
        arm.update(q, np.zeros(7))
        mujoco.mj_jacSite(model, data, jacp, jacr, site)
        np.testing.assert_allclose(arm.J[:3], jacp, rtol=0, atol=TOL)
        np.testing.assert_allclose(arm.J[3:], jacr, rtol=0, atol=TOL)
        np.testing.assert_allclose(arm.x, data.site_xpos[site], rtol=0, atol=TOL)
        np.testing.assert_allclose(arm.R, data.site_xmat[site].reshape(3, 3), rtol=0, atol=TOL)


def test_gear_scene_has_the_same_arm_dynamics():
    """The task scenes add only fixed geometry: the arm's dynamics equal the free scene's."""
    free_model = build_scene("free").model
    free_data = mujoco.MjData(free_model)
    gear_model = build_scene("gear").model
    gear_data = mujoco.MjData(gear_model)
    for q in _random_configurations(3, seed=3):
        for m, d in ((free_model, free_data), (gear_model, gear_data)):
            d.qpos[:] = q
            d.qvel[:] = 0.0
            mujoco.mj_forward(m, d)
        np.testing.assert_allclose(gear_data.qfrc_bias, free_data.qfrc_bias, rtol=0, atol=1e-12)


def test_one_held_part_type_shared_by_sim_and_controller():
    """The simulator's parts are panda_spec's, and held_part_inertia gives the controller the same ones."""
    assert GEAR is panda_spec.GEAR_PART and PEG is panda_spec.PEG_PART
    assert held_part_inertia("gear") is GEAR
    assert held_part_inertia("peg") is PEG
    assert held_part_inertia("none") is None
    for bad in ("anvil", "", "Gear"):
        with pytest.raises(ValueError, match="held_part must be one of"):
            held_part_inertia(bad)
    # the peg's TCP is its tip, 3 cm from the gear's bore mouth: the arm models must differ there
    q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    gear_x = ArmModel(part=held_part_inertia("gear")).tcp_position(q)
    peg_x = ArmModel(part=held_part_inertia("peg")).tcp_position(q)
    dz = float(panda_spec.PEG_TCP_IN_HAND[2] - panda_spec.TCP_IN_HAND[2])
    assert abs(np.linalg.norm(peg_x - gear_x) - abs(dz)) < 1e-9
