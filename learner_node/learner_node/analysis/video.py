"""A rendered episode of a run's deterministic controller (GIF), for run summaries. In process, no ROS:
the episode is the evaluation's own (``RolloutRunner.run_episode``: the same scene, friction draw,
controller and torque law), with frames taken as it runs, so the video ends as the evaluation of the
same start does."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sim_bridge_node.render import _camera, _default_gl_backend, save_gif


def render_run_gif(trainer: Any, path: str | Path, start_seed: int, *, fps: float = 20.0, width: int = 480,
                   height: int = 360) -> dict:
    """Run ``trainer``'s deterministic controller (its policy, its run's law) from ``start_seed`` as its
    evaluation does and write a GIF; returns the episode's final depth, success and distance."""
    if trainer.cfg.task == "block":
        raise ValueError(f"videos are made for the arm tasks, not {trainer.cfg.task!r}")
    from learner_node.trainer import make_evaluator

    _default_gl_backend()
    import mujoco

    runner = trainer.runner
    env = runner.env
    every = max(1, round(1.0 / (fps * env.model.opt.timestep)))
    renderer = mujoco.Renderer(env.model, height=height, width=width)
    frames: list[np.ndarray] = []
    steps = [0]
    cam = None

    def take() -> None:
        nonlocal cam
        if steps[0] % every == 0:
            cam = cam or _camera(env)
            renderer.update_scene(env.data, camera=cam)
            frames.append(renderer.render().copy())
        steps[0] += 1

    runner.on_step = take
    try:
        record = runner.run_episode(make_evaluator(trainer.policy), None, start_seed, None)
    finally:
        runner.on_step = None
        renderer.close()
    save_gif(frames, path, fps=fps)
    return {"insertion_depth": env.insertion_depth, "max_depth": float(record.depth.max()),
            "success": bool(record.final_success), "final_distance": float(record.final_distance),
            "frames": len(frames), "faults": record.faults}
