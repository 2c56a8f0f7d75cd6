"""The render_scene entry point writes a PNG that shows the scene and a GIF of an episode."""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="libosmesa6 not installed")


def _render(args: list[str]) -> None:
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa",
           "PYTHONPATH": os.pathsep.join(str(ROOT / p) for p in ("nf_core", "nf_controller_node", "sim_bridge_node"))}
    subprocess.run([sys.executable, "-m", "sim_bridge_node.render", *args], check=True, env=env, timeout=120,
                   capture_output=True)


def test_png_shows_gear_and_shaft(tmp_path):
    out = tmp_path / "gear.png"
    _render(["--task", "gear", "--out", str(out), "--width", "320", "--height", "240"])
    image = np.asarray(Image.open(out).convert("RGB")).astype(int)
    assert image.shape == (240, 320, 3)
    assert image.std() > 20  # not a blank frame
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    orange = (r > 180) & (g > 90) & (g < 200) & (b < 90)  # the gear
    assert orange.sum() > 200


def test_gif_of_an_episode(tmp_path):
    out = tmp_path / "block.gif"
    _render(["--task", "block", "--out", str(out), "--width", "160", "--height", "120", "--seconds", "0.3"])
    with Image.open(out) as gif:
        assert gif.n_frames >= 5
        assert gif.size == (160, 120)
