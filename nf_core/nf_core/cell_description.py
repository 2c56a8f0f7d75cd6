"""The robot description of a cell as URDF: the Panda (example-robot-data's URDF, its meshes as file://
URLs), the task's part fixed to the hand and its fixture fixed to the base, drawn as primitives. This is
what ``robot_description`` carries, so a viewer (Foxglove's 3D panel, rviz2) shows the arm carrying the
part onto the fixture. ROS-free.
"""

from __future__ import annotations

import re
from pathlib import Path

from nf_core import panda_spec
from nf_core.task_spec import TaskSpec

BASE_LINK = "panda_link0"
PART_LINK = "part"
FIXTURE_LINK = "fixture"
CLAMP_LINK = "clamp"
PART_COLOUR = "0.95 0.65 0.1 1"  # as the simulator draws them
FIXTURE_COLOUR = "0.75 0.78 0.82 1"


def _vec(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in v)


def _visual(shape: str, xyz, colour: str) -> str:
    return (f'<visual><origin xyz="{_vec(xyz)}" rpy="0 0 0"/><geometry>{shape}</geometry>'
            f'<material name=""><color rgba="{colour}"/></material></visual>')


def _fixed_link(name: str, parent: str, xyz, visuals: list[str]) -> str:
    return (f'<link name="{name}">{"".join(visuals)}</link>'
            f'<joint name="{name}_joint" type="fixed"><parent link="{parent}"/><child link="{name}"/>'
            f'<origin xyz="{_vec(xyz)}" rpy="0 0 0"/></joint>')


def cell_urdf(task: TaskSpec, arm_urdf: str | Path | None = None) -> str:
    """URDF of the Panda (``arm_urdf``: default example-robot-data's) holding ``task``'s part over its fixture."""
    path = Path(arm_urdf or panda_spec.panda_urdf_path())
    text = path.read_text()
    # package://example-robot-data/robots/panda_description/... -> file://<its folder>/...
    description = path.resolve().parent.parent
    text = re.sub(r'package://[^"]*?/panda_description', f"file://{description}", text)
    part, fixture = task.part, task.fixture
    held = part.inertia()
    if part.kind == "gear":  # a ring: the outer cylinder (the bore is left to the imagination of the viewer)
        part_visual = _visual(f'<cylinder radius="{part.outer_radius:.6g}" length="{part.thickness:.6g}"/>',
                              held.com_in_hand, PART_COLOUR)
    else:
        part_visual = _visual(f'<cylinder radius="{part.radius:.6g}" length="{part.length:.6g}"/>',
                              held.com_in_hand, PART_COLOUR)
    x, y, top = (float(v) for v in task.top)
    if part.kind == "gear":
        pin_bottom = top - fixture.shaft_length
        fixture_visuals = [
            _visual(f'<cylinder radius="{fixture.shoulder_radius:.6g}" length="{pin_bottom:.6g}"/>',
                    (0.0, 0.0, 0.5 * pin_bottom), FIXTURE_COLOUR),
            _visual(f'<cylinder radius="{fixture.shaft_radius:.6g}" length="{fixture.shaft_length:.6g}"/>',
                    (0.0, 0.0, 0.5 * (pin_bottom + top)), FIXTURE_COLOUR),
        ]
    else:  # the hole's block, drawn solid with its mouth as the top face
        side = 2.0 * (fixture.hole_half_width + 0.0275)
        fixture_visuals = [_visual(f'<box size="{side:.6g} {side:.6g} {top:.6g}"/>', (0.0, 0.0, 0.5 * top),
                                   FIXTURE_COLOUR)]
    extra = [_fixed_link(PART_LINK, panda_spec.HAND_FRAME, (0.0, 0.0, 0.0), [part_visual]),
             _fixed_link(FIXTURE_LINK, BASE_LINK, (x, y, 0.0), fixture_visuals)]
    if task.clamp is not None:
        c = task.clamp
        size = (2 * c.half_thickness, 2 * c.half_length, c.top)
        extra.append(_fixed_link(CLAMP_LINK, BASE_LINK, (c.center_x, y, 0.0),
                                 [_visual(f'<box size="{_vec(size)}"/>', (0.0, 0.0, 0.5 * c.top), FIXTURE_COLOUR)]))
    end = text.rindex("</robot>")
    return text[:end] + "\n  " + "\n  ".join(extra) + "\n" + text[end:]


def link_names(urdf: str) -> list[str]:
    """The links a URDF declares, in order."""
    return re.findall(r'<link name="([^"]+)"', urdf)

