"""The driver's free-space error against franky-sim with the arm joints' Coulomb friction removed
(issue 14): what is left is the error of the controller's arm model (and of franky-sim's own
gravity compensation), not friction / stiffness.

``FrankySim(frictionless=True)`` runs ``python -m nf_bringup.testing.franky --frictionless``:
franky-sim's MuJoCo FR3 built as its console script builds it, with ``frictionloss`` of the seven
arm joints zeroed and nothing else changed. With friction, the same loop is measured by
``tests/test_franka_driver.py::test_converges_in_free_space_to_x_ref_with_limits_respected``.
The numbers (docs/hardware.md): ``python -m pytest tests/test_franka_model_error.py -q -s``.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from franka_driver.loop import reset_policy
from franka_driver.robot_model import FR3, PANDA
from nf_bringup.testing import franky as rig
from nf_bringup.testing.franky import FrankySim
from nf_core import panda_spec

from franky import DriverRig

pylibfranka = pytest.importorskip("pylibfranka")

STEP = np.array([0.03, -0.02, -0.03])  # m, 47 mm: the step of the friction test
S, D = 3000.0, 150.0  # N/m, N s/m: the friction test's spring
S_STIFF, D_STIFF = 8000.0, 150.0  # after convergence; a 47 mm step at 8000 N/m saturates the wrist


@pytest.fixture(scope="module")
def frictionless(tmp_path_factory):
    with FrankySim(tmp_path_factory.mktemp("franky") / "franky-sim.log", frictionless=True) as s:
        yield s


def test_launcher_changes_only_the_arm_joints_friction():
    """The compiled MuJoCo model with and without ``--frictionless``: only ``dof_frictionloss`` of the
    seven arm joints differs (zero instead of 0.25-1.14 Nm); the fingers keep theirs."""
    from franky_sim.mujoco_simulator import MujocoSimulator

    models = []
    for frictionless in (False, True):
        sim = MujocoSimulator(enable_visualization=False)
        sim.init()
        rig.add_robot(sim, frictionless)
        sim.start()
        names = [j.get("name") for j in rig.arm_joints(sim.scene)]
        models.append((sim.model, rig.joint_frictionloss(sim.model, names)))
        sim.cleanup()
    (ref, ref_friction), (mod, mod_friction) = models
    assert ref_friction == pytest.approx([1.137, 1.137, 1.137, 1.137, 0.763, 0.44, 0.248])
    assert mod_friction == [0.0] * 7
    differ = []
    for name in dir(ref):
        a = getattr(ref, name)
        if name.startswith("_") or not isinstance(a, np.ndarray | int | float):
            continue
        b = getattr(mod, name)
        if np.shape(a) != np.shape(b) or not np.array_equal(a, b, equal_nan=True):
            differ.append(name)
    assert differ == ["dof_frictionloss"]
    changed = np.flatnonzero(ref.dof_frictionloss != mod.dof_frictionloss)
    assert len(changed) == 7 and np.all(mod.dof_frictionloss[changed] == 0.0)


def _step(rig: DriverRig, goal: np.ndarray, stages: list[tuple[float, float, float]]) -> list[float]:
    """Drive the TCP to ``goal`` with each (S, D, robot seconds) in turn (identity flow); the distance
    (m) of the true TCP (the FR3 description's kinematics) from ``goal`` at the end of each stage."""
    truth = FR3.arm_model(panda_spec.GEAR_PART)
    errors = []
    rig.start()
    for version, (stiffness, damping, seconds) in enumerate(stages, 1):
        params = reset_policy(goal, stiffness, damping)
        params.version = version
        rig.loop.set_policy(params)
        rig.run_for(seconds)
        errors.append(float(np.linalg.norm(truth.tcp_position(rig.q) - goal)))
    assert rig.driver.exceptions == 0, rig.driver.last_error
    assert not rig.loop.fault
    taus, limits = rig.torques_and_limits()
    assert np.all(np.abs(taus[1:]) <= limits[:-1] + 1e-9)
    assert np.all(np.abs(np.diff(taus, axis=0)) <= 1.0 + 1e-9)  # 1000 Nm/s at 1 kHz
    return errors


def test_identified_fr3_model_converges_within_1mm_without_joint_friction(frictionless):
    text = frictionless.log_path.read_text()
    assert re.findall(r"fr3_joint\d ([\d.]+)", text) == ["0.000"] * 7, text  # the launcher's report
    rig = DriverRig(idle_mode="policy")
    assert rig.spec is FR3
    try:
        goal = rig.x0 + STEP
        error, stiff = _step(rig, goal, [(S, D, 3.0), (S_STIFF, D_STIFF, 1.0)])
    finally:
        rig.stop()
    print(f"\nwithout joint friction, FR3 description: {error * 1e3:.3f} mm from x_ref after 3 s at "
          f"S = {S:.0f} N/m; {stiff * 1e3:.3f} mm after 1 s more at S = {S_STIFF:.0f} N/m")
    assert error < 0.001, f"{error * 1e3:.3f} mm from x_ref"
    # What is left is a constant force, so it shrinks as 1/S: franky-sim compensates gravity with
    # its own Pinocchio model of the arm, which misses 0.29 N at the TCP against its MuJoCo arm.
    assert stiff < 0.6 * error


def test_panda_description_on_the_fr3_ends_as_close(frictionless):
    """The Panda description forced onto the FR3 (``identify`` refuses it) against the FR3's own,
    the same step on the same arm. On a Franka the robot adds g(q) itself (gravity compensation off
    in the controller), so the law uses only the description's kinematics, which are the FR3's: the
    masses that make the Panda description wrong never reach the command."""
    errors = {}
    x0 = None
    for spec, offset in ((PANDA, -STEP), (FR3, 0.0 * STEP)):  # there and back again
        rig = DriverRig(idle_mode="policy", spec=spec)
        assert rig.identification.spec is FR3 and rig.spec is spec
        try:
            x0 = rig.x0 if x0 is None else x0
            errors[spec.kind] = _step(rig, x0 + offset, [(S, D, 3.0)])[0]
            q = rig.q.copy()
        finally:
            rig.stop()
    print(f"\nwithout joint friction, S = {S:.0f} N/m, 3 s: Panda description {errors['panda'] * 1e3:.3f} mm, "
          f"FR3 description {errors['fr3'] * 1e3:.3f} mm from x_ref")
    assert errors["panda"] < 0.001 and errors["fr3"] < 0.001
    assert abs(errors["panda"] - errors["fr3"]) < 0.0002
    panda, fr3 = PANDA.arm_model(panda_spec.GEAR_PART), FR3.arm_model(panda_spec.GEAR_PART)
    panda.update(q, np.zeros(7))
    fr3.update(q, np.zeros(7))
    assert np.allclose(panda.x, fr3.x, atol=1e-9) and np.allclose(panda.J, fr3.J, atol=1e-9)
    assert np.allclose(panda.R, fr3.R, atol=1e-9)
    assert np.abs(panda.g - fr3.g).max() > 0.5  # Nm: the masses do differ
