"""Which Franka arm is connected, and its Pinocchio model, limits and joint names. ROS-free.

pylibfranka 0.21.3 does not expose the robot's URDF (libfranka's ``getRobotModel``), so the
description comes from a package matching the arm: the FR3's ``fr3.urdf`` shipped with
``franky-sim`` (the same file its MuJoCo model and the robot server derive from) or the Panda's
``panda.urdf`` of ``example-robot-data``. ``identify`` then checks the choice against what the
robot itself serves: libfranka's mass matrix ``Model.mass(state)`` (computed by the robot's own
dynamics model, with its configured end-effector load) and its end-effector pose ``O_T_EE``. A
model that does not match is refused with the numbers, never used silently.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from nf_controller_node.arm_model import ArmModel
from nf_core import panda_spec

ROBOT_KINDS = ("auto", "fr3", "panda")
# Relative Frobenius error of the mass matrix below which a description matches the robot, and
# how much worse the other description must be for "auto" to decide (measured on franky-sim's FR3:
# FR3 0.4 %, Panda 3.5 %).
MASS_MATCH = 0.015
MASS_SEPARATION = 3.0
POSE_MATCH = 0.002  # m: flange position of the description vs the robot's O_T_EE


@dataclass(frozen=True)
class ArmSpec:
    """A Franka arm type: its description file, names in it, and datasheet limits."""

    kind: str
    joint_names: tuple[str, ...]
    finger_joint_names: tuple[str, ...]
    hand_frame: str
    q_min: np.ndarray  # rad
    q_max: np.ndarray  # rad
    dq_max: np.ndarray  # rad/s
    torque_limits: np.ndarray  # Nm
    torque_rate_limit: float  # Nm/s

    def urdf_path(self) -> str:
        """The description file of this arm type (raises FileNotFoundError naming the package)."""
        if self.kind == "panda":
            return panda_spec.panda_urdf_path()
        try:
            import franky_sim
        except ImportError:
            raise FileNotFoundError("fr3.urdf comes with the 'franky-sim' package (make setup installs it)") from None
        path = Path(franky_sim.__file__).parent / "assets" / "fr3.urdf"
        if not path.is_file():
            raise FileNotFoundError(f"fr3.urdf not found at {path}")
        return str(path)

    def arm_model(self, part: panda_spec.HeldPartInertia | None, armature: np.ndarray | None = None) -> ArmModel:
        """The controller's Pinocchio model of this arm holding ``part``."""
        return ArmModel(self.urdf_path(), armature=armature, part=part, joint_names=self.joint_names,
                        finger_joint_names=self.finger_joint_names, hand_frame=self.hand_frame)

    def fit_loop(self, loop: Any) -> None:
        """Give a ``ControlLoop`` this arm's limits (its defaults are the Panda's): the plausibility
        bounds of joint states (the arm's ranges + the same margin, its velocity limits x the same
        factor), torque limits no larger than the arm's, and the joint-limit springs at its ranges."""
        margin = loop.q_max - panda_spec.Q_MAX
        loop.q_min = self.q_min - margin
        loop.q_max = self.q_max + margin
        loop.dq_max = self.dq_max * (loop.dq_max / panda_spec.DQ_MAX)
        law = loop.controller.law
        law.torque_limits[:] = np.minimum(law.torque_limits, self.torque_limits)
        law.set_joint_limits(self.q_min, self.q_max)


# Franka's datasheets (FR3: "Robot and interface specifications", Panda: the same for the Panda).
FR3 = ArmSpec(
    kind="fr3",
    joint_names=tuple(f"fr3_joint{i}" for i in range(1, 8)),
    finger_joint_names=("fr3_finger_joint1", "fr3_finger_joint2"),
    hand_frame="fr3_hand",
    q_min=np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
    q_max=np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
    dq_max=np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26]),
    torque_limits=np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0]),
    torque_rate_limit=1000.0,
)
PANDA = ArmSpec(
    kind="panda",
    joint_names=panda_spec.JOINT_NAMES,
    finger_joint_names=panda_spec.FINGER_JOINT_NAMES,
    hand_frame=panda_spec.HAND_FRAME,
    q_min=panda_spec.Q_MIN.copy(),
    q_max=panda_spec.Q_MAX.copy(),
    dq_max=panda_spec.DQ_MAX.copy(),
    torque_limits=panda_spec.TORQUE_LIMITS.copy(),
    torque_rate_limit=panda_spec.TORQUE_RATE_LIMIT,
)
SPECS = {"fr3": FR3, "panda": PANDA}


class WrongRobotModelError(RuntimeError):
    """The description does not match the connected robot (or the robot could not be identified)."""


@dataclass
class Identification:
    """Result of ``identify``: the chosen spec and the evidence."""

    spec: ArmSpec
    mass_error: dict[str, float]  # kind -> relative mass-matrix error against the robot's model
    pose_error: float  # m, flange position of the chosen description vs the robot's

    def summary(self) -> str:
        """One line for the log."""
        errors = ", ".join(f"{k} {v * 100:.2f} %" for k, v in self.mass_error.items())
        return (f"{self.spec.kind} (mass matrix vs the robot's model: {errors}; flange position "
                f"{self.pose_error * 1e3:.2f} mm)")


def _column_major(values: Sequence[float], rows: int, cols: int) -> np.ndarray:
    return np.asarray(values, dtype=np.float64).reshape(rows, cols, order="F")


def _bare_model(spec: ArmSpec, state: Any) -> tuple[pin.Model, int]:
    """Pinocchio model of ``spec`` with fingers locked, no armature, and the robot's configured
    extra load (``m_load`` at ``F_x_Cload`` in the flange frame) added, as libfranka's model has it;
    also the id of the flange frame (joint 7's frame at the hand)."""
    arm = ArmModel(spec.urdf_path(), armature=np.zeros(7), part=None, joint_names=spec.joint_names,
                   finger_joint_names=spec.finger_joint_names, hand_frame=spec.hand_frame)
    model = arm.model
    hand = model.frames[model.getFrameId(spec.hand_frame)]
    m_load = float(getattr(state, "m_load", 0.0) or 0.0)
    if m_load > 0.0:
        # F (flange) and the hand frame share their origin; the hand is turned -45 deg about z.
        flange = hand.placement * pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, np.pi / 4), np.zeros(3))
        inertia = pin.Inertia(m_load, np.asarray(state.F_x_Cload, float), _column_major(state.I_load, 3, 3))
        model.appendBodyToJoint(hand.parentJoint, flange.act(inertia), pin.SE3.Identity())
    return model, model.getFrameId(spec.hand_frame)


def mass_error(spec: ArmSpec, state: Any, robot_mass: np.ndarray) -> tuple[float, float]:
    """(relative mass-matrix error, flange position error in m) of ``spec`` against the robot."""
    model, hand_id = _bare_model(spec, state)
    data = model.createData()
    q = np.asarray(state.q, dtype=np.float64)
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    rel = float(np.linalg.norm(M - robot_mass) / np.linalg.norm(robot_mass))
    pin.framesForwardKinematics(model, data, q)
    O_T_EE = _column_major(state.O_T_EE, 4, 4)
    F_T_EE = _column_major(state.F_T_EE, 4, 4)
    O_T_F = O_T_EE @ np.linalg.inv(F_T_EE)
    pose = float(np.linalg.norm(data.oMf[hand_id].translation - O_T_F[:3, 3]))
    return rel, pose


def identify(kind: str, state: Any, robot_model: Any) -> Identification:
    """The arm spec for parameter ``kind`` (auto | fr3 | panda), checked against the robot.

    ``state``: a libfranka RobotState; ``robot_model``: ``Robot.load_model()``. Raises
    ``WrongRobotModelError`` when the requested description does not match (mass matrix or flange
    position), or when "auto" cannot tell FR3 and Panda apart.
    """
    if kind not in ROBOT_KINDS:
        raise ValueError(f"robot_model must be one of {ROBOT_KINDS}, got {kind!r}")
    robot_mass = _column_major(robot_model.mass(state), 7, 7)
    results = {name: mass_error(spec, state, robot_mass) for name, spec in SPECS.items()}
    errors = {name: r[0] for name, r in results.items()}
    if kind == "auto":
        ranked = sorted(errors, key=errors.get)
        best, other = ranked[0], ranked[1]
        if errors[best] > MASS_MATCH or errors[other] < MASS_SEPARATION * errors[best]:
            raise WrongRobotModelError(f"cannot tell the arm type from its mass matrix: "
                                  f"{', '.join(f'{k} {v * 100:.2f} %' for k, v in errors.items())}; "
                                  f"set robot_model to fr3 or panda")
        kind = best
    found = Identification(SPECS[kind], errors, results[kind][1])
    if errors[kind] > MASS_MATCH:
        raise WrongRobotModelError(f"the {kind} description does not match the connected robot: {found.summary()} "
                              f"(match below {MASS_MATCH * 100:.1f} %)")
    if found.pose_error > POSE_MATCH:
        raise WrongRobotModelError(f"the {kind} description's flange is {found.pose_error * 1e3:.1f} mm from the "
                              f"robot's O_T_EE (at most {POSE_MATCH * 1e3:.0f} mm)")
    return found
