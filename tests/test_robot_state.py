"""See the cell: ``robot_state`` publishes the cell's URDF (the Panda, the task's part, its fixture) and the
arm's transforms from joint_states; ``fleet_view`` serves both to a Foxglove client, and the recorder
puts both in the bag."""

from __future__ import annotations

import json
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from sensor_msgs.msg import JointState
from test_fleet_view import MESSAGE_DATA, SUBPROTOCOLS, _free_port
from websockets.sync.client import connect

from nf_bringup.robot_state import CellFrames
from nf_controller_node.arm_model import ArmModel
from nf_core import panda_spec, qos
from nf_core.cell_description import cell_urdf, link_names
from nf_core.task_spec import load_task

from ros_testing import RosProcess, allocate_domain_id

SIDE = Path(__file__).resolve().parents[1] / "config" / "tasks" / "examples" / "gear_side_fixture.yaml"
Q = np.array([0.1, -0.3, 0.05, -2.2, 0.02, 2.0, 0.8])


@pytest.mark.parametrize("task", ["gear", "peg", "gear_clamp", str(SIDE)])
def test_the_cell_urdf_carries_the_part_where_the_controller_has_its_tcp(task):
    spec = load_task(task)
    urdf = cell_urdf(spec)
    names = link_names(urdf)
    assert {"panda_link0", "panda_hand", "part", "fixture"} <= set(names)
    assert ("clamp" in names) == (spec.clamp is not None)
    for mesh in re.findall(r'filename="file://([^"]+)"', urdf):
        assert Path(mesh).is_file(), mesh
    assert "package://" not in urdf
    frames = CellFrames(urdf)
    assert frames.set_joints(list(panda_spec.JOINT_NAMES), Q)
    poses = {name: (xyz, quat) for name, xyz, quat in frames.poses()}
    # the part link sits on the hand; its TCP there is the controller's TCP (Pinocchio on the same URDF)
    xyz, quat = poses["part"]
    x, y, z, w = quat
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    held = spec.part.inertia()
    np.testing.assert_allclose(xyz + rot @ held.tcp_in_hand, ArmModel(part=held).tcp_position(Q), atol=1e-9)
    np.testing.assert_allclose(poses["fixture"][0], [spec.top[0], spec.top[1], 0.0], atol=1e-12)
    # another driver's joint names: the first seven values in order
    assert frames.set_joints([f"fr3_joint{i}" for i in range(1, 8)], Q)
    np.testing.assert_allclose(dict((n, p) for n, p, _ in frames.poses())["part"], xyz, atol=1e-12)
    assert not frames.set_joints(list(panda_spec.JOINT_NAMES), np.full(7, np.nan))


class JointStates:
    """This test's driver: the arm's joint states at 50 Hz, joint 1 turning slowly."""

    def __init__(self, domain: int) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("test_driver", context=self.ctx)
        self.pub = self.node.create_publisher(JointState, "joint_states", qos.STATE)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        t = 0.0
        while not self.stop.wait(0.02):
            t += 0.02
            msg = JointState(name=list(panda_spec.JOINT_NAMES), position=list(Q + [0.2 * np.sin(t), 0, 0, 0, 0, 0, 0]))
            msg.header.stamp = self.node.get_clock().now().to_msg()
            self.pub.publish(msg)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


@pytest.mark.ros
@pytest.mark.timeout(90)
def test_a_foxglove_client_sees_the_cell_and_the_bag_holds_it(tmp_path):
    from mcap.reader import make_reader

    domain, port = allocate_domain_id(), _free_port()
    recorder = RosProcess(["-m", "nf_bags.record", "-o", str(tmp_path / "bag"), "--topics", "/robot_description",
                           "/tf"], domain, log_path=tmp_path / "recorder.log")
    state = RosProcess(["-m", "nf_bringup.robot_state", "--ros-args", "-p", f"task:={SIDE}"], domain,
                       log_path=tmp_path / "robot_state.log")
    view = RosProcess(["-m", "nf_bringup.fleet_view", "--ros-args", "-p", f"port:={port}", "-p",
                       f"run_dir:={tmp_path}", "-p", "discovery_period:=0.2"], domain, log_path=tmp_path / "view.log")
    driver = JointStates(domain)
    try:
        t0 = time.monotonic()
        while True:  # the server listens once the process has imported rclpy and foxglove
            assert view.alive() and state.alive(), view.log() + state.log()
            assert time.monotonic() - t0 < 20, view.log()
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.1)
        with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=5) as ws:
            channels: dict[int, dict] = {}
            deadline = time.monotonic() + 20
            while {"/robot_description", "/tf"} - {c["topic"] for c in channels.values()}:
                assert time.monotonic() < deadline, (channels, view.log())
                op = json.loads(ws.recv(timeout=20))
                if op["op"] == "advertise":
                    channels.update({c["id"]: c for c in op["channels"] if c["topic"] in ("/robot_description", "/tf")})
            by_topic = {c["topic"]: c for c in channels.values()}
            assert by_topic["/tf"]["schemaName"] == "foxglove.FrameTransforms", by_topic["/tf"]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c, "channelId": c} for c in channels]}))
            got: dict[str, bytes] = {}
            deadline = time.monotonic() + 10  # the description comes again every 2 s, transforms at 30 Hz
            while len(got) < 2:
                assert time.monotonic() < deadline, got.keys()
                frame = ws.recv(timeout=10)
                if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                    got[channels[int.from_bytes(frame[1:5], "little")]["topic"]] = frame[13:]
        urdf = json.loads(got["/robot_description"])["data"]
        assert '<link name="part">' in urdf and '<link name="fixture">' in urdf
        for frame_id in (b"panda_link0", b"panda_hand", b"part", b"fixture"):  # protobuf keeps strings as bytes
            assert frame_id in got["/tf"], frame_id
    finally:
        driver.close()
        for proc in (view, state):
            assert proc.stop() == 0, proc.log()
        assert recorder.stop() == 0, recorder.log()
    bags = list((tmp_path / "bag").glob("*.mcap"))
    with open(bags[0], "rb") as f:  # the mcap library's own reader
        counts: dict[str, int] = {}
        schemas: dict[str, str] = {}
        for schema, channel, _ in make_reader(f).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            schemas[channel.topic] = schema.name
    assert counts.get("/robot_description") == 1 and counts.get("/tf", 0) >= 5, counts
    assert schemas == {"/robot_description": "std_msgs/msg/String", "/tf": "tf2_msgs/msg/TFMessage"}, schemas
