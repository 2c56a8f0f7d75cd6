"""The Panda arm as a MuJoCo model, loaded from the URDF that ``example-robot-data`` ships.

The URDF is the same file Pinocchio loads, so the rigid-body dynamics of both agree. This module
turns it into an ``mujoco.MjSpec`` ready for torque control:

- ``package://`` mesh paths rewritten to the installed meshes (collision STL meshes are used
  for both contact and drawing: MuJoCo cannot read the Collada visual meshes);
- finger joints removed, fingers welded to the hand at ``panda_spec.FINGER_OPENING`` (their
  mass stays on the hand), so ``nq == nv == 7``;
- joint armature and viscous damping from ``panda_spec``, torque motors on ``panda_joint1..7``
  with ``ctrlrange = +-TORQUE_LIMITS``, 1 ms time step;
- every body, joint, geom and actuator named; contact filtering by bit masks so that arm links
  never collide with each other, only with the fixed world (see ``CONTACT_*``).
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from nf_core import panda_spec

TIMESTEP = 0.001  # s, 1 kHz

# Contact bit masks: two geoms touch if (contype_a & conaffinity_b) or (contype_b & conaffinity_a).
# Moving parts (arm links, held part, block) have contype=MOVING, conaffinity=0: they never
# touch each other. Fixed world geoms (table, fixtures) have contype=0, conaffinity=MOVING.
CONTACT_MOVING = 2

# Finger joint axes in the hand frame (URDF): finger 1 opens along +y, finger 2 along -y.
_FINGER_AXES = {"panda_leftfinger": np.array([0.0, 1.0, 0.0]), "panda_rightfinger": np.array([0.0, -1.0, 0.0])}

ARM_RGBA = np.array([0.93, 0.93, 0.95, 1.0])
HAND_RGBA = np.array([0.25, 0.25, 0.28, 1.0])


def panda_urdf_path() -> Path:
    """Path of ``panda.urdf`` inside the installed ``example-robot-data`` (the file Pinocchio loads)."""
    return Path(panda_spec.panda_urdf_path())


def _urdf_with_absolute_meshes(urdf_path: Path) -> str:
    """URDF text with ``package://example-robot-data/`` resolved and MuJoCo compiler options added."""
    text = urdf_path.read_text()
    share_dir = urdf_path.parents[3]  # .../share/example-robot-data
    text = text.replace("package://example-robot-data/", f"{share_dir.as_posix()}/")
    compiler = (
        '<mujoco><compiler fusestatic="false" discardvisual="true" strippath="false" '
        'balanceinertia="false"/></mujoco>'
    )
    head_end = text.index(">", text.index("<robot")) + 1
    return text[:head_end] + compiler + text[head_end:]


def load_panda_spec() -> mujoco.MjSpec:
    """The Panda as an ``MjSpec``: locked fingers, damping, armature, torque motors, named geoms.

    The world body holds only the arm; scenes add the table, fixtures, lights and the held part.
    """
    spec = mujoco.MjSpec.from_string(_urdf_with_absolute_meshes(panda_urdf_path()))
    spec.modelname = "panda"
    spec.compiler.discardvisual = False  # the URDF's visuals are gone; keep what scenes add
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST

    # Lock the fingers: delete their joints and weld the finger bodies at the set opening.
    for name in panda_spec.FINGER_JOINT_NAMES:
        spec.delete(spec.joint(name))
    for eq in list(spec.equalities):  # a <mimic> tag may have become an equality
        spec.delete(eq)
    for body_name, axis in _FINGER_AXES.items():
        body = spec.body(body_name)
        body.pos = np.asarray(body.pos) + panda_spec.FINGER_OPENING * axis

    for i, name in enumerate(panda_spec.JOINT_NAMES):
        joint = spec.joint(name)
        joint.armature = float(panda_spec.JOINT_ARMATURE[i])
        joint.damping = [float(panda_spec.JOINT_DAMPING[i]), 0.0, 0.0]  # linear term only
        joint.frictionloss = 0.0
        joint.range = [float(panda_spec.Q_MIN[i]), float(panda_spec.Q_MAX[i])]
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        act = spec.add_actuator()
        act.name = f"{name}_motor"
        act.target = name
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.gainprm[0] = 1.0
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = [-float(panda_spec.TORQUE_LIMITS[i]), float(panda_spec.TORQUE_LIMITS[i])]

    for body in spec.bodies:
        for k, geom in enumerate(body.geoms):
            geom.name = f"{body.name}_collision_{k}"
            geom.contype = CONTACT_MOVING
            geom.conaffinity = 0
            hand_part = body.name in ("panda_hand", *_FINGER_AXES)
            geom.rgba = HAND_RGBA if hand_part else ARM_RGBA
    return spec


def set_weld_inertia(body: mujoco.MjsBody, mass: float, com: np.ndarray, inertia: np.ndarray) -> None:
    """Give ``body`` an explicit mass, centre of mass (body frame) and diagonal inertia about it."""
    body.explicitinertial = True
    body.mass = float(mass)
    body.ipos = np.asarray(com, dtype=float)
    body.iquat = [1.0, 0.0, 0.0, 0.0]
    body.inertia = np.diag(np.asarray(inertia, dtype=float)) if np.ndim(inertia) == 2 else inertia
