"""Pinocchio model of the Panda holding the gear: kinematics, Jacobian, gravity and mass matrix.

Built once from the example-robot-data URDF (the file MuJoCo loads too): finger joints locked,
the gear's inertia appended to joint 7, a ``gear_tcp`` frame at the bore mouth, rotor
armature on the joints. ``update(q, dq)`` then only computes (no allocation of model data).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from . import panda_spec


class ArmModel:
    """Panda + held gear. After ``update(q, dq)``: ``x``, ``xdot``, ``R``, ``J`` (6x7), ``g`` are current."""

    def __init__(
        self,
        urdf_path: str | None = None,
        armature: np.ndarray | None = None,
        gear_mass: float = panda_spec.GEAR_MASS,
    ) -> None:
        full = pin.buildModelFromUrdf(urdf_path or panda_spec.panda_urdf_path())
        q_full = pin.neutral(full)
        lock = []
        for name in panda_spec.FINGER_JOINT_NAMES:
            jid = full.getJointId(name)
            q_full[full.joints[jid].idx_q] = panda_spec.FINGER_OPENING
            lock.append(jid)
        model = pin.buildReducedModel(full, lock, q_full)
        names = [model.names[i] for i in range(1, model.njoints)]
        if names != list(panda_spec.JOINT_NAMES):
            raise ValueError(f"unexpected joints in the URDF after locking fingers: {names}")

        hand = model.frames[model.getFrameId(panda_spec.HAND_FRAME)]
        joint7 = hand.parentJoint
        jMhand = hand.placement  # hand frame in joint-7 frame
        if gear_mass > 0.0:
            R = jMhand.rotation
            inertia = pin.Inertia(
                gear_mass, jMhand.act(panda_spec.GEAR_COM_IN_HAND), R @ panda_spec.gear_inertia() @ R.T
            )
            model.appendBodyToJoint(joint7, inertia, pin.SE3.Identity())
        tcp = pin.SE3(np.eye(3), panda_spec.TCP_IN_HAND)
        self.tcp_id = model.addFrame(
            pin.Frame(panda_spec.TCP_FRAME, joint7, model.getFrameId(panda_spec.HAND_FRAME),
                      jMhand * tcp, pin.FrameType.OP_FRAME)
        )
        arm = panda_spec.JOINT_ARMATURE if armature is None else np.asarray(armature, dtype=float)
        model.armature = np.array(arm, dtype=float).copy()

        self.model = model
        self.data = model.createData()
        self.nq = model.nq
        self.J = np.zeros((6, self.nq))  # [linear; angular] at the TCP, world-aligned axes
        self.g = np.zeros(self.nq)  # gravity torque, Nm
        self.x = np.zeros(3)  # TCP position in the base frame, m
        self.xdot = np.zeros(3)  # TCP linear velocity, m/s
        self.R = np.eye(3)  # hand orientation in the base frame

    def update(self, q: np.ndarray, dq: np.ndarray) -> None:
        """Compute TCP pose, velocity, Jacobian and gravity torque for joint state (q [rad], dq [rad/s])."""
        model, data = self.model, self.data
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacement(model, data, self.tcp_id)
        self.J[:] = pin.getFrameJacobian(model, data, self.tcp_id, pin.LOCAL_WORLD_ALIGNED)
        self.g[:] = pin.computeGeneralizedGravity(model, data, q)
        oMtcp = data.oMf[self.tcp_id]
        self.x[:] = oMtcp.translation
        self.R[:] = oMtcp.rotation
        np.dot(self.J[:3], dq, out=self.xdot)

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """Joint-space mass matrix M(q) including rotor armature, kg m^2 (symmetric)."""
        M = pin.crba(self.model, self.data, q)
        return np.triu(M) + np.triu(M, 1).T

    def kinetic_energy(self, q: np.ndarray, dq: np.ndarray) -> float:
        """1/2 dq^T M(q) dq, J."""
        M = pin.crba(self.model, self.data, q)  # upper triangle is filled
        Ms = np.triu(M) + np.triu(M, 1).T
        return 0.5 * float(dq @ Ms @ dq)

    def tcp_position(self, q: np.ndarray) -> np.ndarray:
        """TCP position (m) for a configuration, without touching the cached state's Jacobian."""
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.tcp_id].translation.copy()
