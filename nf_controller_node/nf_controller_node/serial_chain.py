"""Kinematics, TCP Jacobian and gravity torque of a serial chain of revolute joints, in one compiled call.

The arm model's per-tick work (TCP position and orientation, the 6 x n Jacobian at the TCP in
world-aligned axes, the gravity torque g(q)) took four Pinocchio calls through its Python bindings.
Back to back they cost about 7 us; right after a 1 ms wait, as in a 1 kHz driver, about 31 us at
the median and 92 us at p99 on this project's VM, more than the flow step itself. This module reads
the same model's numbers once (each joint's placement in its parent, axis, link mass and centre of
mass, the TCP frame's placement in the last joint, the gravity vector) and evaluates them in a
single numba kernel over preallocated arrays. A test holds it equal to Pinocchio to 1e-12.

Only chains where joint i's parent is joint i-1 and every joint is a 1-DoF revolute joint are
supported (the Panda and the FR3); :meth:`SerialChain.from_pinocchio` returns None for any other
model, and the arm model then keeps using Pinocchio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0)}


@njit(cache=True)
def chain_kinematics(q, joint_rot, joint_pos, axis, mass, com, tcp_rot, tcp_pos, gravity, o_rot, o_pos,
                     J, x, R, g):  # pragma: no cover - compiled
    """Write the TCP position ``x`` (3), orientation ``R`` (3x3), Jacobian ``J`` (6xn: linear rows
    then angular, world-aligned axes at the TCP) and gravity torque ``g`` (n) for joint angles ``q``.
    ``o_rot`` (n,3,3) and ``o_pos`` (n,3) are work arrays: each joint frame's pose in the base."""
    n = q.shape[0]
    for i in range(n):
        # joint frame before its own rotation: parent pose * placement
        if i == 0:
            for r in range(3):
                for c in range(3):
                    o_rot[0, r, c] = joint_rot[0, r, c]
                o_pos[0, r] = joint_pos[0, r]
        else:
            for r in range(3):
                acc = o_pos[i - 1, r]
                for k in range(3):
                    acc += o_rot[i - 1, r, k] * joint_pos[i, k]
                x[r] = acc  # scratch: the new origin (x is rewritten below)
                for c in range(3):
                    s = 0.0
                    for k in range(3):
                        s += o_rot[i - 1, r, k] * joint_rot[i, k, c]
                    R[r, c] = s  # scratch
            for r in range(3):
                o_pos[i, r] = x[r]
                for c in range(3):
                    o_rot[i, r, c] = R[r, c]
        # rotation by q[i] about the joint's own axis (Rodrigues), applied on the right
        ax, ay, az = axis[i, 0], axis[i, 1], axis[i, 2]
        cq, sq = math.cos(q[i]), math.sin(q[i])
        vq = 1.0 - cq
        r00, r01, r02 = cq + ax * ax * vq, ax * ay * vq - az * sq, ax * az * vq + ay * sq
        r10, r11, r12 = ay * ax * vq + az * sq, cq + ay * ay * vq, ay * az * vq - ax * sq
        r20, r21, r22 = az * ax * vq - ay * sq, az * ay * vq + ax * sq, cq + az * az * vq
        for r in range(3):
            a0, a1, a2 = o_rot[i, r, 0], o_rot[i, r, 1], o_rot[i, r, 2]
            o_rot[i, r, 0] = a0 * r00 + a1 * r10 + a2 * r20
            o_rot[i, r, 1] = a0 * r01 + a1 * r11 + a2 * r21
            o_rot[i, r, 2] = a0 * r02 + a1 * r12 + a2 * r22
    last = n - 1
    for r in range(3):
        acc = o_pos[last, r]
        for k in range(3):
            acc += o_rot[last, r, k] * tcp_pos[k]
        x[r] = acc
        for c in range(3):
            s = 0.0
            for k in range(3):
                s += o_rot[last, r, k] * tcp_rot[k, c]
            R[r, c] = s
    for j in range(n):
        zx = o_rot[j, 0, 0] * axis[j, 0] + o_rot[j, 0, 1] * axis[j, 1] + o_rot[j, 0, 2] * axis[j, 2]
        zy = o_rot[j, 1, 0] * axis[j, 0] + o_rot[j, 1, 1] * axis[j, 1] + o_rot[j, 1, 2] * axis[j, 2]
        zz = o_rot[j, 2, 0] * axis[j, 0] + o_rot[j, 2, 1] * axis[j, 1] + o_rot[j, 2, 2] * axis[j, 2]
        dx, dy, dz = x[0] - o_pos[j, 0], x[1] - o_pos[j, 1], x[2] - o_pos[j, 2]
        J[0, j] = zy * dz - zz * dy
        J[1, j] = zz * dx - zx * dz
        J[2, j] = zx * dy - zy * dx
        J[3, j] = zx
        J[4, j] = zy
        J[5, j] = zz
        # g_j = -sum_{i >= j} m_i gravity . (z_j x (c_i - p_j)) = -(gravity x z_j) . sum m_i (c_i - p_j)
        mx = my = mz = 0.0
        for i in range(j, n):
            m = mass[i]
            cx = o_pos[i, 0] + o_rot[i, 0, 0] * com[i, 0] + o_rot[i, 0, 1] * com[i, 1] + o_rot[i, 0, 2] * com[i, 2]
            cy = o_pos[i, 1] + o_rot[i, 1, 0] * com[i, 0] + o_rot[i, 1, 1] * com[i, 1] + o_rot[i, 1, 2] * com[i, 2]
            cz = o_pos[i, 2] + o_rot[i, 2, 0] * com[i, 0] + o_rot[i, 2, 1] * com[i, 1] + o_rot[i, 2, 2] * com[i, 2]
            mx += m * (cx - o_pos[j, 0])
            my += m * (cy - o_pos[j, 1])
            mz += m * (cz - o_pos[j, 2])
        gx = gravity[1] * zz - gravity[2] * zy
        gy = gravity[2] * zx - gravity[0] * zz
        gz = gravity[0] * zy - gravity[1] * zx
        g[j] = -(gx * mx + gy * my + gz * mz)


@dataclass(frozen=True)
class SerialChain:
    """The numbers of a serial revolute chain that :func:`chain_kinematics` needs, plus its work arrays."""

    joint_rot: np.ndarray  # (n, 3, 3) joint i's frame in joint i-1's (the base for i = 0) at q_i = 0
    joint_pos: np.ndarray  # (n, 3)
    axis: np.ndarray  # (n, 3) rotation axis in the joint's own frame (unit)
    mass: np.ndarray  # (n,) kg: everything rigidly attached to joint i (held part included)
    com: np.ndarray  # (n, 3) its centre of mass in joint i's frame, m
    tcp_rot: np.ndarray  # (3, 3) the TCP frame in the last joint's frame
    tcp_pos: np.ndarray  # (3,)
    gravity: np.ndarray  # (3,) m/s^2 in the base frame
    o_rot: np.ndarray  # (n, 3, 3) work
    o_pos: np.ndarray  # (n, 3) work

    @property
    def args(self) -> tuple[np.ndarray, ...]:
        """The arguments of ``chain_kinematics`` between ``q`` and the outputs."""
        return (self.joint_rot, self.joint_pos, self.axis, self.mass, self.com, self.tcp_rot, self.tcp_pos,
                self.gravity, self.o_rot, self.o_pos)

    @classmethod
    def from_pinocchio(cls, model: Any, tcp_frame_id: int) -> SerialChain | None:
        """The chain of a Pinocchio model up to frame ``tcp_frame_id`` (which must hang on the last
        joint), or None when the model is not a serial chain of 1-DoF revolute joints."""
        n = model.njoints - 1
        if n < 1 or model.nq != n or model.nv != n:
            return None
        joint_rot, joint_pos = np.zeros((n, 3, 3)), np.zeros((n, 3))
        axis, mass, com = np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3))
        for i in range(1, n + 1):
            joint = model.joints[i]
            kind = joint.shortname()
            if model.parents[i] != i - 1 or joint.idx_q != i - 1 or joint.nq != 1:
                return None
            if kind in _AXES:
                axis[i - 1] = _AXES[kind]
            elif kind == "JointModelRevoluteUnaligned":
                axis[i - 1] = np.asarray(joint.extract().axis, dtype=float)
            else:
                return None
            placement = model.jointPlacements[i]
            joint_rot[i - 1], joint_pos[i - 1] = placement.rotation, placement.translation
            inertia = model.inertias[i]
            mass[i - 1], com[i - 1] = inertia.mass, inertia.lever
        frame = model.frames[tcp_frame_id]
        if frame.parentJoint != n:
            return None
        return cls(joint_rot, joint_pos, axis, mass, com, np.array(frame.placement.rotation),
                   np.array(frame.placement.translation), np.array(model.gravity.linear, dtype=float),
                   np.zeros((n, 3, 3)), np.zeros((n, 3)))
