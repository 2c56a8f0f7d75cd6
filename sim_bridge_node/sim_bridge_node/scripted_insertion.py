"""A scripted (not learned) insertion for demonstrations, tests and benchmarks.

A Cartesian impedance on the TCP (Jacobian transpose) holding the hand pointing straight down,
with gravity compensation from MuJoCo's bias forces. The target moves on a path: a smooth move
to just above the fixture mouth, a short settle, then a slow descent to ``push_depth`` below the
goal. Used to check that contacts are honest: the same push seats an aligned part and jams a
misaligned one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HAND_DOWN = np.diag([1.0, -1.0, -1.0])  # hand axes in the world: x forward, z pointing down


@dataclass(frozen=True)
class PushGains:
    """Impedance gains of the scripted push."""

    stiffness: float = 1500.0  # N/m
    damping: float = 80.0  # N s/m
    rot_stiffness: float = 60.0  # Nm/rad
    rot_damping: float = 4.0  # Nm s/rad
    joint_damping: float = 2.0  # Nm s/rad (null space)
    block_stiffness: float = 300.0  # N/m
    block_damping: float = 40.0  # N s/m


def push_torque(env, target: np.ndarray, gains: PushGains = PushGains()) -> np.ndarray:
    """Joint torques (block: forces) pulling the TCP towards ``target`` with the hand down."""
    if env.task == "block":
        force = gains.block_stiffness * (target - env.x)[[0, 2]] - gains.block_damping * env.dq
        return force + env.bias_torques
    jac = env.tcp_jacobian()
    rot = env.tcp_rotation
    rot_err = 0.5 * (np.cross(rot[:, 0], HAND_DOWN[:, 0]) + np.cross(rot[:, 1], HAND_DOWN[:, 1])
                     + np.cross(rot[:, 2], HAND_DOWN[:, 2]))
    dq = env.dq
    force = gains.stiffness * (target - env.x) - gains.damping * (jac[:3] @ dq)
    torque = gains.rot_stiffness * rot_err - gains.rot_damping * (jac[3:] @ dq)
    return jac[:3].T @ force + jac[3:].T @ torque - gains.joint_damping * dq + env.bias_torques


def insertion_target(env, t: float, start: np.ndarray, offset: np.ndarray, push_depth: float = 0.005,
                     approach_time: float = 0.8, settle_time: float = 0.3, speed: float = 0.02,
                     hover: float = 0.005) -> np.ndarray:
    """Target on the scripted path at time ``t`` (s) from ``start``; ``offset`` shifts the goal."""
    goal = env.goal_position + offset
    above = goal.copy()
    above[2] = env.scene.insertion_top + hover
    if t < approach_time:
        s = t / approach_time
        return start + (above - start) * (s * s * (3.0 - 2.0 * s))
    descent = max(0.0, t - approach_time - settle_time) * speed
    return above - np.array([0.0, 0.0, min(descent, above[2] - goal[2] + push_depth)])


def run_insertion(env, offset=(0.0, 0.0, 0.0), seconds: float = 3.0, push_depth: float = 0.005,
                  speed: float = 0.02, callback=None) -> dict:
    """Run the scripted insertion from the current state; return depth, success and contact stats.

    ``callback(env)`` is called after every step (e.g. to record frames).
    """
    start = env.x
    offset = np.asarray(offset, dtype=float)
    max_pen = 0.0
    steps = round(seconds / env.model.opt.timestep)
    for k in range(steps):
        t = k * env.model.opt.timestep
        env.step(push_torque(env, insertion_target(env, t, start, offset, push_depth, speed=speed)))
        max_pen = max(max_pen, env.penetration)
        if callback is not None:
            callback(env)
    return {
        "depth": env.insertion_depth,
        "success": env.success,
        "max_penetration": max_pen,
        "penetration": env.penetration,
        "contact_force": env.contact_force,
        "x": env.x,
    }
