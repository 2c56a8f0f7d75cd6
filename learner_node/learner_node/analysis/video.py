"""A rendered episode of a deterministic flow controller (GIF), for run summaries. In process:
the same ``FlowController`` and MuJoCo scene the nodes use, no ROS."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_core import panda_spec
from nf_core.policy_params import PolicyParameters
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.held_parts import PEG
from sim_bridge_node.render import _camera, _default_gl_backend, save_gif


def render_policy_gif(params: PolicyParameters, task: str, path: str | Path, *, start_seed: int | None = None,
                      seconds: float = 5.0, fps: float = 20.0, width: int = 480, height: int = 360) -> dict:
    """Run the deterministic controller of ``params`` for ``seconds`` on ``task`` (gear/peg) from
    ``start_seed`` and write a GIF; returns the episode's final depth, success and distance."""
    if task not in ("gear", "peg"):
        raise ValueError(f"videos are made for the arm tasks gear and peg, not {task!r}")
    _default_gl_backend()
    import mujoco

    env = InsertionEnv(task)
    env.reset(seed=start_seed)
    arm = ArmModel(part=PEG if task == "peg" else panda_spec.GEAR_PART)
    ctrl = FlowController(arm, FlowEvaluator.from_params(params))
    every = max(1, round(1.0 / (fps * env.model.opt.timestep)))
    steps = round(seconds / env.model.opt.timestep)
    renderer = mujoco.Renderer(env.model, height=height, width=width)
    frames: list[np.ndarray] = []
    try:
        cam = _camera(env)
        for k in range(steps + 1):
            if k % every == 0:
                renderer.update_scene(env.data, camera=cam)
                frames.append(renderer.render().copy())
            if k < steps:
                env.step(ctrl.step(env.q, env.dq).copy())
    finally:
        renderer.close()
    save_gif(frames, path, fps=fps)
    return {"insertion_depth": env.insertion_depth, "success": env.success,
            "final_distance": float(np.linalg.norm(env.x - env.goal_position)), "frames": len(frames),
            "fault": ctrl.fault}
