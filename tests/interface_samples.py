"""Deterministic, non-trivial instances of every nf_msgs interface, and a deep field comparison.

Used by both ends of the DDS round-trip test, so what one process sends the other can rebuild.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus, PolicyParameters, RolloutChunk, TaskStatus
from nf_msgs.srv import ResetSim

from nf_core.flow_spec import FlowArchitecture


def _series(n: int, seed: int) -> list[float]:
    return np.random.default_rng(seed).normal(size=n).tolist()


def policy_parameters() -> PolicyParameters:
    arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
    m = PolicyParameters(version=7, dim=3, n_flow=2, n_hidden=16, activation="gelu")
    m.weights = _series(arch.n_params, 1)
    m.log_std = [math.log(1.5)]
    m.stiffness = np.diag([4.0, 4.0, 4.0]).reshape(-1).tolist()
    m.damping = np.eye(3).reshape(-1).tolist()
    m.x_ref = [0.5, 0.0, 0.25]
    m.potential_force_bound, m.k_rot, m.d_rot, m.joint_damping = 60.0, 30.0, 3.0, 0.5
    m.stiffness_floor, m.held_part = 2.5, "peg"
    return m


def rollout_chunk() -> RolloutChunk:
    n = 50
    m = RolloutChunk(episode_id=2**40 + 3, seq=4, final=True, n_chunks=5, policy_version=7, dim=3)
    m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id = 12, 345, "panda_link0"
    m.t = (np.arange(n) * 0.01).tolist()
    for i, name in enumerate(("x", "xdot", "u_mean", "action")):
        setattr(m, name, _series(3 * n, 10 + i))
    m.log_prob, m.reward, m.insertion_depth = _series(n, 20), _series(n, 21), _series(n, 22)
    return m


def controller_status() -> ControllerStatus:
    m = ControllerStatus(mode=ControllerStatus.MODE_SAFE_HOLD, fault="stale joint state (12.0 ms)")
    m.header.frame_id = "panda_link0"
    m.policy_version, m.episode_id, m.lyapunov, m.lyapunov_rate = 3, 9, 0.25, -0.5
    m.x, m.x_ref, m.torque_norm, m.deadline_misses = [0.1, 0.2, 0.3], [0.5, 0.0, 0.25], 12.5, 17
    return m


def task_status() -> TaskStatus:
    m = TaskStatus(task="gear", insertion_depth=0.0171, success=True, contact_force=3.25)
    m.part_position = [0.5, 0.0, 0.2329]
    return m


def reset_request() -> ResetSim.Request:
    return ResetSim.Request(seed=42, q=[0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])


def reset_response() -> ResetSim.Response:
    return ResetSim.Response(success=True, message="ok", q=_series(7, 30), x=[0.5, 0.0, 0.35])


def episode_goal() -> RunEpisode.Goal:
    return RunEpisode.Goal(policy_version=7, seed=-1, noise_seed=11, duration=5.0, deterministic=True)


def episode_feedback() -> RunEpisode.Feedback:
    return RunEpisode.Feedback(t=1.25, lyapunov=0.75, insertion_depth=0.004, chunks_sent=2)


def episode_result() -> RunEpisode.Result:
    return RunEpisode.Result(
        completed=True, message="done", episode_id=11, n_chunks=5, episode_return=-12.5,
        success=True, insertion_depth=0.0175, final_distance=0.0021,
    )


TOPIC_SAMPLES = {
    "/test/policy_parameters": policy_parameters,
    "/test/rollout": rollout_chunk,
    "/test/controller_status": controller_status,
    "/test/task_status": task_status,
}


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Field paths where two ROS messages differ (exact comparison, arrays elementwise)."""
    if type(a) is not type(b) and not (_is_seq(a) and _is_seq(b)):
        return [f"{path}: type {type(a).__name__} != {type(b).__name__}"]
    if hasattr(a, "get_fields_and_field_types"):
        out: list[str] = []
        for field in a.get_fields_and_field_types():
            out += differences(getattr(a, field), getattr(b, field), f"{path}.{field}")
        return out
    if _is_seq(a):
        a, b = list(a), list(b)
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def _is_seq(x: Any) -> bool:
    return isinstance(x, list | tuple | np.ndarray) or type(x).__name__ == "array"
