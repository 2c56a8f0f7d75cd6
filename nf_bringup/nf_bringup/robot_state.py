"""``robot_state``: the cell's robot description and the arm's transforms, from ``joint_states``, as ROS 2's
``robot_state_publisher`` does, for viewers (Foxglove's 3D panel, rviz2) and bags.

- ``robot_description`` (std_msgs/String, transient local: a viewer or recorder that joins later gets it):
  the cell's URDF (``cell_urdf``: the Panda, the task's part in the hand, its fixture);
- ``tf`` (tf2_msgs/TFMessage) at ``rate`` Hz while joint states come in: every link of that URDF relative
  to ``panda_link0``, at the latest state (the joints by name, or the first seven values in order when
  the driver names them otherwise, as an FR3's ``fr3_joint*``).

Both names are relative, so an arm under a namespace gets ``<ns>/tf`` and ``<ns>/robot_description``.
It listens best effort (the newest state only): it never holds back the arm's state writer. The URDF
(``cell_urdf``) and its forward kinematics (``CellFrames``) are ROS-free.

    python -m nf_bringup.robot_state --ros-args -p task:=gear -p rate:=30.0
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from nf_core import panda_spec
from nf_core.ros_runtime import declare_read_only, run_node
from nf_core.task_spec import TaskSpec, load_task
from nf_core.topics import JOINT_STATES
from tf2_msgs.msg import TFMessage

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


DESCRIPTION = "robot_description"
TF = "tf"
DESCRIPTION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
STATE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
TF_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
PARAMETERS = {
    "task": ("gear", "the cell: a built-in task or a task file (config/tasks/README.md)"),
    "rate": (30.0, "Hz: transforms published at most this often"),
}


class CellFrames:
    """Forward kinematics of a cell's URDF (Pinocchio): the pose of every link in the base frame. ROS-free."""

    def __init__(self, urdf: str) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model = pin.buildModelFromXML(urdf)
        self.data = self.model.createData()
        self.links = [f.name for f in self.model.frames
                      if f.type == pin.FrameType.BODY and f.name != BASE_LINK]
        self._frame_ids = [self.model.getFrameId(n) for n in self.links]
        self.arm_joints = list(panda_spec.JOINT_NAMES)
        self._q_index = {n: self.model.joints[self.model.getJointId(n)].idx_q
                         for n in (*panda_spec.JOINT_NAMES, *panda_spec.FINGER_JOINT_NAMES)}
        self.q = self._neutral()

    def _neutral(self) -> np.ndarray:
        q = self._pin.neutral(self.model)
        for name in panda_spec.FINGER_JOINT_NAMES:
            q[self._q_index[name]] = panda_spec.FINGER_OPENING
        return q

    def set_joints(self, names: list[str], positions: np.ndarray) -> bool:
        """Take an arm state: the joints by name, else the first seven values in order. False if unusable."""
        positions = np.asarray(positions, dtype=float)
        if not np.all(np.isfinite(positions)):
            return False
        if set(self.arm_joints) <= set(names):
            values = [positions[names.index(n)] for n in self.arm_joints]
        elif positions.size >= len(self.arm_joints):
            values = positions[:len(self.arm_joints)]
        else:
            return False
        for name, value in zip(self.arm_joints, values, strict=True):
            self.q[self._q_index[name]] = value
        return True

    def poses(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """(link, position (m), quaternion x y z w) of every link in the base frame, at the last state."""
        pin = self._pin
        pin.framesForwardKinematics(self.model, self.data, self.q)
        out = []
        for name, fid in zip(self.links, self._frame_ids, strict=True):
            placement = self.data.oMf[fid]
            quat = pin.Quaternion(placement.rotation)
            out.append((name, placement.translation.copy(), np.array([quat.x, quat.y, quat.z, quat.w])))
        return out


class RobotStateNode(Node):
    """Publishes the cell's description once and the arm's transforms from its joint states."""

    def __init__(self) -> None:
        super().__init__("robot_state")
        p = declare_read_only(self, PARAMETERS)
        if not p["rate"] > 0.0:
            raise ValueError(f"rate must be > 0 Hz, got {p['rate']}")
        urdf = cell_urdf(load_task(p["task"]))
        self.frames = CellFrames(urdf)
        self.description = self.create_publisher(String, DESCRIPTION, DESCRIPTION_QOS)
        self.description.publish(String(data=urdf))
        self.tf = self.create_publisher(TFMessage, TF, TF_QOS)
        self._latest: JointState | None = None
        self.create_subscription(JointState, JOINT_STATES, self._on_state, STATE_QOS)
        self.create_timer(1.0 / p["rate"], self._publish)
        self.get_logger().info(f"robot description of task {p['task']} ({len(urdf)} characters, "
                               f"{len(self.frames.links)} links); transforms at up to {p['rate']:g} Hz")

    def _on_state(self, msg: JointState) -> None:
        self._latest = msg

    def _publish(self) -> None:
        msg, self._latest = self._latest, None
        if msg is None or not self.frames.set_joints(list(msg.name), np.asarray(msg.position)):
            return
        out = TFMessage()
        for name, xyz, quat in self.frames.poses():
            t = TransformStamped()
            t.header.stamp = msg.header.stamp
            t.header.frame_id = BASE_LINK
            t.child_frame_id = name
            t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(v) for v in xyz)
            (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
             t.transform.rotation.w) = (float(v) for v in quat)
            out.transforms.append(t)
        self.tf.publish(out)


def main(argv: list[str] | None = None) -> int:
    """Console script ``robot_state``."""
    return run_node(RobotStateNode, "robot_state", __doc__.split("\n\n")[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
