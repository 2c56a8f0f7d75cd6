"""Pinocchio model of the Panda holding a part: kinematics, Jacobian, gravity and mass matrix.

Built once from the example-robot-data URDF (the file MuJoCo loads too): finger joints locked,
the held part's inertia appended to joint 7 (the gear by default), a ``gear_tcp`` frame at the
part's tool-centre point, rotor armature on the joints. ``update(q, dq)`` then only computes
(no allocation of model data). The per-tick part (TCP pose, Jacobian, gravity) runs in one compiled
call (``serial_chain``) when the model is a serial revolute chain, as the Panda and the FR3 are.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from nf_core import panda_spec

from .serial_chain import SerialChain, chain_kinematics


class ArmModel:
    """Panda + held gear. After ``update(q, dq)``: ``x``, ``xdot``, ``R``, ``J`` (6x7), ``g`` are current."""

    def __init__(
        self,
        urdf_path: str | None = None,
        armature: np.ndarray | None = None,
        part: panda_spec.HeldPartInertia | None = panda_spec.GEAR_PART,
        *,
        joint_names: tuple[str, ...] = panda_spec.JOINT_NAMES,
        finger_joint_names: tuple[str, ...] = panda_spec.FINGER_JOINT_NAMES,
        hand_frame: str = panda_spec.HAND_FRAME,
    ) -> None:
        """``part``: mass, com_in_hand, inertia, tcp_in_hand of the held part (any object with these
        attributes, e.g. the simulator's held-part description); None = empty hand, TCP at the gear's.
        ``joint_names``, ``finger_joint_names``, ``hand_frame``: the names in another arm's URDF
        (e.g. the FR3's ``fr3_joint1..7``, ``fr3_finger_joint1/2``, ``fr3_hand``); default the Panda's."""
        full = pin.buildModelFromUrdf(urdf_path or panda_spec.panda_urdf_path())
        q_full = pin.neutral(full)
        lock = []
        for name in finger_joint_names:
            jid = full.getJointId(name)
            q_full[full.joints[jid].idx_q] = panda_spec.FINGER_OPENING
            lock.append(jid)
        model = pin.buildReducedModel(full, lock, q_full)
        names = [model.names[i] for i in range(1, model.njoints)]
        if names != list(joint_names):
            raise ValueError(f"unexpected joints in the URDF after locking fingers: {names}, want {list(joint_names)}")
        self.joint_names = tuple(names)

        hand = model.frames[model.getFrameId(hand_frame)]
        joint7 = hand.parentJoint
        jMhand = hand.placement  # hand frame in joint-7 frame
        if part is not None and part.mass > 0.0:
            R = jMhand.rotation
            inertia = pin.Inertia(
                float(part.mass), jMhand.act(np.asarray(part.com_in_hand, float)), R @ part.inertia @ R.T
            )
            model.appendBodyToJoint(joint7, inertia, pin.SE3.Identity())
        # the part as one line (gear | peg | none | a task file's part): a policy learned with another part in
        # the hand is refused
        self.held_part = "none" if part is None else str(getattr(part, "name", "") or getattr(part, "kind", "gear"))
        tcp_in_hand = panda_spec.TCP_IN_HAND if part is None else part.tcp_in_hand
        tcp = pin.SE3(np.eye(3), np.asarray(tcp_in_hand, float))
        self.tcp_id = model.addFrame(
            pin.Frame(panda_spec.TCP_FRAME, joint7, model.getFrameId(hand_frame),
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
        self.chain = SerialChain.from_pinocchio(model, self.tcp_id)  # None: Pinocchio computes each tick
        self.chain_args = self.chain.args if self.chain is not None else ()  # for fused compiled callers

    def update(self, q: np.ndarray, dq: np.ndarray) -> None:
        """Compute TCP pose, velocity, Jacobian and gravity torque for joint state (q [rad], dq [rad/s]).

        The attributes are rewritten in place (with Pinocchio for a model that is not a serial chain:
        rebound to views into its data); they stay valid until the next call. Copy what you keep.
        """
        self.kinematics(q)
        self.xdot = self.J[:3] @ dq

    def kinematics(self, q: np.ndarray) -> None:
        """Like ``update`` without the TCP velocity (``xdot`` is left as it was)."""
        if self.chain is not None:
            chain_kinematics(q, *self.chain_args, self.J, self.x, self.R, self.g)
            return
        model, data, fid = self.model, self.data, self.tcp_id
        pin.computeJointJacobians(model, data, q)
        oMtcp = pin.updateFramePlacement(model, data, fid)
        self.J = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        self.g = pin.computeGeneralizedGravity(model, data, q)
        self.x = oMtcp.translation
        self.R = oMtcp.rotation

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """g(q) (Nm) into ``g``, returned (with the compiled chain the whole ``kinematics`` is redone:
        one call). For the safe hold, which needs no Jacobian: ``g`` then stays the gravity of the
        latest usable state for everyone who reads it."""
        if self.chain is not None:
            self.kinematics(q)
        else:
            self.g = pin.computeGeneralizedGravity(self.model, self.data, q).copy()
        return self.g

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
