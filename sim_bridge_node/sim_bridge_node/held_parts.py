"""Parts held rigidly by the Panda hand: the gear (main task) and the cylindrical peg.

Each part is a child body of ``panda_hand`` with its own explicit mass and inertia (its geoms
carry no mass), contact geometry made of convex pieces, and a TCP site at the centre of the
part's leading face (the point the controller drives to the goal).
"""

from __future__ import annotations

import mujoco
import numpy as np

from nf_core import panda_spec
from nf_core.task_spec import BUILTIN_PARTS, Part
from sim_bridge_node.panda_model import CONTACT_MOVING, set_weld_inertia

GEAR_SEGMENTS = 16  # box pieces around the bore; the bore is the regular 16-gon of inradius 15 mm
GEAR_TEETH = 24  # drawn only, no contact
GEAR_RGBA = np.array([0.95, 0.65, 0.1, 1.0])
PEG_RGBA = np.array([0.2, 0.45, 0.95, 1.0])

HeldPart = panda_spec.HeldPartInertia  # names and hand-frame geometry of the part the hand holds
GEAR = panda_spec.GEAR_PART
PEG = panda_spec.PEG_PART


def _solid_geom(body: mujoco.MjsBody, name: str, rgba: np.ndarray) -> mujoco.MjsGeom:
    geom = body.add_geom()
    geom.name = name
    geom.contype = CONTACT_MOVING
    geom.conaffinity = 0
    geom.rgba = rgba
    return geom


def _visual_geom(body: mujoco.MjsBody, name: str, rgba: np.ndarray) -> mujoco.MjsGeom:
    geom = body.add_geom()
    geom.name = name
    geom.contype = 0
    geom.conaffinity = 0
    geom.group = 1
    geom.rgba = rgba
    return geom


def add_gear(hand: mujoco.MjsBody, part: Part | None = None) -> HeldPart:
    """Weld the gear ring of ``part`` (default: the gear task's) to ``hand``: body ``gear``, site
    ``gear_tcp``, 16 box segments.

    Body frame = hand axes, origin at the gear's centre (its COM). Each segment is a box whose
    inner face lies exactly at the bore radius; the boxes are as wide as the outer polygon
    needs, so neighbours overlap outside the bore and the bore stays a clean 16-gon.
    """
    part = part or Part()
    r_in, r_out, depth = part.bore_radius, part.outer_radius, part.thickness
    held = part.inertia()
    body = hand.add_body()
    body.name = held.body
    body.pos = held.com_in_hand
    set_weld_inertia(body, held.mass, np.zeros(3), held.inertia)
    half_radial = 0.5 * (r_out - r_in)
    half_tangent = r_out * np.tan(np.pi / GEAR_SEGMENTS)
    for k in range(GEAR_SEGMENTS):
        angle = 2.0 * np.pi * k / GEAR_SEGMENTS
        geom = _solid_geom(body, f"gear_segment_{k}", GEAR_RGBA)
        geom.type = mujoco.mjtGeom.mjGEOM_BOX
        geom.size = [half_radial, half_tangent, 0.5 * depth]
        radius = r_in + half_radial
        geom.pos = [radius * np.cos(angle), radius * np.sin(angle), 0.0]
        geom.quat = [np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]
    tooth = 0.004  # m, drawn tooth height
    for k in range(GEAR_TEETH):
        angle = 2.0 * np.pi * (k + 0.5) / GEAR_TEETH
        geom = _visual_geom(body, f"gear_tooth_{k}", GEAR_RGBA * [0.8, 0.8, 0.8, 1.0])
        geom.type = mujoco.mjtGeom.mjGEOM_BOX
        geom.size = [0.5 * tooth + 0.001, 0.0025, 0.5 * depth * 0.9]
        radius = r_out + 0.5 * tooth - 0.001
        geom.pos = [radius * np.cos(angle), radius * np.sin(angle), 0.0]
        geom.quat = [np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]
    site = body.add_site()
    site.name = held.tcp_site
    site.pos = held.tcp_in_hand - held.com_in_hand
    site.size = [0.003, 0.003, 0.003]
    site.rgba = [1.0, 0.1, 0.1, 1.0]
    return held


def add_peg(hand: mujoco.MjsBody, part: Part | None = None) -> HeldPart:
    """Weld the peg of ``part`` (default: the peg task's) to ``hand``: body ``peg`` (one convex cylinder),
    site ``peg_tcp`` at its tip."""
    part = part or BUILTIN_PARTS["peg"]
    held = part.inertia()
    body = hand.add_body()
    body.name = held.body
    body.pos = held.com_in_hand
    set_weld_inertia(body, held.mass, np.zeros(3), held.inertia)
    geom = _solid_geom(body, "peg_cylinder", PEG_RGBA)
    geom.type = mujoco.mjtGeom.mjGEOM_CYLINDER
    geom.size = [part.radius, 0.5 * part.length, 0.0]
    site = body.add_site()
    site.name = held.tcp_site
    site.pos = held.tcp_in_hand - held.com_in_hand
    site.size = [0.003, 0.003, 0.003]
    site.rgba = [1.0, 0.1, 0.1, 1.0]
    return held
