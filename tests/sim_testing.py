"""Helpers for tests of the MuJoCo environments: the full physics state and a scripted push."""

from __future__ import annotations

import mujoco
import numpy as np

from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scripted_insertion import push_torque


def full_state(env: InsertionEnv) -> np.ndarray:
    """MuJoCo's full physics state of ``env`` (positions, velocities, activations, time, ...)."""
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(env.model, spec))
    mujoco.mj_getState(env.model, env.data, state, spec)
    return state


def push_rollout(env: InsertionEnv, seed: int | None, steps: int) -> np.ndarray:
    """Reset with ``seed``, then ``steps`` steps pushing 5 cm above the goal: the full state after each."""
    env.reset(seed)
    target = env.goal_position + [0.0, 0.0, 0.05]
    out = []
    for _ in range(steps):
        env.step(push_torque(env, target))
        out.append(full_state(env))
    return np.array(out)
