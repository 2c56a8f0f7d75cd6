"""Offscreen pictures of the scenes and short animated GIFs of episodes (console script ``render_scene``).

Needs an OpenGL backend; on a headless machine set ``MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa``
(``main`` sets them when no display and no backend is configured). GIFs are written with Pillow,
which matplotlib already depends on.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from sim_bridge_node.scripted_insertion import push_torque, run_insertion


def _default_gl_backend() -> None:
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "osmesa"
        os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


def _camera(env, overrides: dict | None = None):
    import mujoco

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    params = {**env.scene.camera, **(overrides or {})}
    cam.lookat[:] = params["lookat"]
    cam.distance = params["distance"]
    cam.azimuth = params["azimuth"]
    cam.elevation = params["elevation"]
    return cam


def render_frames(env, n_frames: int = 1, *, width: int = 960, height: int = 720,
                  advance: Callable[[], None] | None = None, camera: dict | None = None) -> list[np.ndarray]:
    """RGB frames (height x width x 3, uint8) of ``env``; ``advance()`` is called between frames."""
    import mujoco

    renderer = mujoco.Renderer(env.model, height=height, width=width)
    try:
        cam = _camera(env, camera)
        frames = []
        for k in range(n_frames):
            if k and advance is not None:
                advance()
            renderer.update_scene(env.data, camera=cam)
            frames.append(renderer.render().copy())
        return frames
    finally:
        renderer.close()


def save_png(frame: np.ndarray, path: str | Path) -> Path:
    """Write one RGB frame as PNG."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(frame).save(path)
    return path


def save_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 25.0) -> Path:
    """Write RGB frames as a looping animated GIF."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f).convert("P", palette=Image.Palette.ADAPTIVE, colors=192) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return path


def render_episode(env, seconds: float = 3.0, fps: float = 20.0, *, width: int = 640, height: int = 480,
                   offset=(0.0, 0.0, 0.0), camera: dict | None = None) -> list[np.ndarray]:
    """Frames of the scripted insertion (``scripted_insertion``) from the environment's current state."""
    import mujoco

    every = max(1, round(1.0 / (fps * env.model.opt.timestep)))
    renderer = mujoco.Renderer(env.model, height=height, width=width)
    try:
        cam = _camera(env, camera)
        frames: list[np.ndarray] = []
        counter = [0]

        def grab(e) -> None:
            if counter[0] % every == 0:
                renderer.update_scene(e.data, camera=cam)
                frames.append(renderer.render().copy())
            counter[0] += 1

        grab(env)
        speed = 0.05 if env.task == "block" else 0.02
        run_insertion(env, offset, seconds=seconds, speed=speed, callback=grab)
        return frames
    finally:
        renderer.close()


def approach_pose(env, height: float = 0.03) -> None:
    """Move the held part (from the current state) to ``height`` above the fixture mouth, for stills."""
    start = env.x
    above = env.goal_position.copy()
    above[2] = env.scene.insertion_top + height
    for k in range(1200):
        s = min(1.0, k / 800.0)
        env.step(push_torque(env, start + (above - start) * (s * s * (3.0 - 2.0 * s))))


def main(argv: Sequence[str] | None = None) -> int:
    """``render_scene --task gear --out docs/images/gear.png`` (``.gif`` renders an episode)."""
    parser = argparse.ArgumentParser(prog="render_scene", description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="gear", choices=("gear", "peg", "block", "free"))
    parser.add_argument("--out", required=True, help="output .png (still) or .gif (episode)")
    parser.add_argument("--seed", type=int, default=-1, help="start seed; negative = fixed start")
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--seconds", type=float, default=4.0, help="episode length for .gif")
    parser.add_argument("--pose", default="approach", choices=("approach", "start"),
                        help="still: part just above the fixture (approach) or the start pose")
    parser.add_argument("--plane", default="vertical", choices=("vertical", "horizontal"))
    args = parser.parse_args(argv)
    _default_gl_backend()
    from sim_bridge_node.env import InsertionEnv

    env = InsertionEnv(args.task, plane=args.plane)
    out = Path(args.out)
    env.reset(seed=args.seed)
    if out.suffix.lower() == ".gif":
        save_gif(render_episode(env, args.seconds, width=args.width, height=args.height), out)
    else:
        if args.pose == "approach" and args.task != "free":
            approach_pose(env)
        save_png(render_frames(env, width=args.width, height=args.height)[0], out)
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
