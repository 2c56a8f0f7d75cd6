"""The live view of the fleet (``nf_bringup.fleet_view``): its ROS-free core, then the node as a
process over real DDS, read by a Foxglove WebSocket client the way Foxglove Studio reads it.

The arms are fakes (this test's node publishes ControllerStatus and RolloutChunk under /arm0 and
/arm1): the subject is the view, and a sim arm would cost seconds of start-up for nothing it checks.
Last, the cell: ``robot_state``'s URDF (the Panda, the task's part, its fixture) and transforms from joint
states, served by the view to a Foxglove client and kept by the recorder."""

from __future__ import annotations

import json
import math
import re
import socket
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from nf_msgs.msg import ControllerStatus, RolloutChunk
from sensor_msgs.msg import JointState
from websockets.sync.client import connect

from nf_bringup.fleet_state import FleetState, LearnerProgress, learner_dir
from nf_bringup.robot_state import CellFrames, cell_urdf, link_names
from nf_controller_node.arm_model import ArmModel
from nf_core import panda_spec, qos
from nf_core.task_spec import load_task

from ros_testing import RosProcess, allocate_domain_id

# foxglove-sdk 0.30's server speaks the Foxglove WebSocket protocol under the name "foxglove.sdk.v1"
# (the frames of "foxglove.websocket.v1"; it refuses a client offering only the old name with HTTP 400).
# Foxglove offers both, as this client does.
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01  # opcode of a binary message frame (server -> client)

METRICS = [
    {"iteration": 1.0, "success_rate": 0.0, "return_mean": -900.0, "wall_seconds": 10.0, "arms_used": 2.0},
    {"iteration": 2.0, "success_rate": 0.5, "return_mean": -400.0, "wall_seconds": 12.0, "arms_used": 2.0,
     "v_loss": float("nan")},
]


def _status(**kw: float) -> dict[str, float]:
    base = dict(mode=1, fault="", policy_version=3, episode_id=5, lyapunov=0.2, lyapunov_rate=-0.1,
                torque_norm=4.0, deadline_misses=0)
    base.update(kw)
    return base


def test_arm_state_follows_status_and_episodes():
    fleet = FleetState(success_depth=0.016)
    assert fleet.status("/arm1", 0.0, **_status())  # a new arm is a change
    assert not fleet.status("/arm1", 0.1, **_status(lyapunov=0.1))  # V alone is not
    assert fleet.status("/arm1", 0.2, **_status(mode=2, fault="joint limit"))
    assert fleet.status("", 0.2, **_status(episode_id=9))  # the root namespace is the arm "/"
    assert not fleet.chunk("/arm1", episode_id=5, final=False, t=[0.0, 0.1], insertion_depth=[0.0, 0.02])
    assert fleet.chunk("/arm1", episode_id=5, final=True, t=[0.2, 0.3], insertion_depth=[0.02, 0.017])
    assert fleet.chunk("/arm1", episode_id=6, final=True, t=[0.3], insertion_depth=[math.nan])
    snap = fleet.snapshot(now=1.0)
    assert [a["arm"] for a in snap["arms"]] == ["/", "/arm1"] and snap["count"] == 2
    arm = snap["arms"][1]
    assert arm["mode"] == "safe_hold" and arm["fault"] == "joint limit" and arm["alive"]
    assert arm["lyapunov"] == 0.2 and arm["episode_time"] == 0.3 and arm["episode_id"] == 6
    assert arm["episodes"] == 2 and arm["success_rate"] == 0.5 and arm["last_success"] is False
    assert arm["last_depth"] is None  # NaN is not JSON
    json.dumps(snap, allow_nan=False)
    assert not fleet.snapshot(now=10.0)["arms"][1]["alive"]  # no status for 9 s


def test_learner_progress_from_the_run_folder(tmp_path):
    run = tmp_path / "runs" / "2026-01-01_00-00-00" / "learner"
    progress = LearnerProgress(tmp_path / "runs")
    assert progress.poll() == (None, False)
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"iterations": 30}))
    (run / "metrics.json").write_text(json.dumps(METRICS))  # NaN as the learner writes it
    (run / "arms.json").write_text(json.dumps({"arms": {"/arm0": {"done": 9}}, "batches": []}))
    assert learner_dir(tmp_path / "runs") == run and learner_dir(run.parent) == run and learner_dir(run) == run
    message, changed = progress.poll()
    assert changed and message["iteration"] == 2 and message["iterations"] == 30
    assert message["success_rate"] == 0.5 and message["seconds_per_iteration"] == 12.0
    assert message["mean_seconds_per_iteration"] == 11.0 and message["seconds_left"] == 28 * 11.0
    assert message["success_history"] == [0.0, 0.5] and message["rollouts_per_arm"] == {"/arm0": {"done": 9}}
    json.dumps(message, allow_nan=False)
    assert progress.poll() == (message, False)  # files unchanged: not read again


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PublisherThread:
    """A node of this test in its own context, publishing from a thread (``_run``) until ``close``."""

    def __init__(self, domain: int, name: str) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


def _wait_for_server(port: int, procs: list[RosProcess], timeout: float) -> None:
    """Until the view's WebSocket server listens (once its process has imported rclpy and foxglove)."""
    t0 = time.monotonic()
    while True:
        for proc in procs:
            assert proc.alive(), proc.log()
        assert time.monotonic() - t0 < timeout, procs[0].log()
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.1)


class FakeArms(PublisherThread):
    """This test's node: /arm0 running and inserting, /arm1 in safe hold and failing, 20 Hz."""

    def __init__(self, domain: int) -> None:
        super().__init__(domain, "fake_arms")
        self.arms = {"/arm0": (ControllerStatus.MODE_RUNNING, "", 0.02),
                     "/arm1": (ControllerStatus.MODE_SAFE_HOLD, "torque limit", 0.001)}
        self.pubs = {ns: (self.node.create_publisher(ControllerStatus, f"{ns}/controller_status", qos.STATE),
                          self.node.create_publisher(RolloutChunk, f"{ns}/rollouts", qos.ROLLOUTS))
                     for ns in self.arms}
        self.thread.start()

    def _run(self) -> None:
        episode = 0
        while not self.stop.wait(0.05):
            episode += 1
            for ns, (mode, fault, depth) in self.arms.items():
                status_pub, chunk_pub = self.pubs[ns]
                status_pub.publish(ControllerStatus(mode=mode, fault=fault, policy_version=7, episode_id=episode,
                                                    lyapunov=0.5, lyapunov_rate=-0.2))
                chunk_pub.publish(RolloutChunk(episode_id=episode, seq=0, final=True, n_chunks=1, dim=3,
                                               t=[0.0, 0.1], insertion_depth=[0.0, depth]))


def _read_until(ws, channels: dict[int, str], want, timeout: float) -> dict[str, dict]:
    """Read message frames (by subscription id = channel id) until ``want(latest)`` holds; the latest
    payload per topic."""
    latest: dict[str, dict] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            frame = ws.recv(timeout=max(0.01, deadline - time.monotonic()))
        except TimeoutError:
            break
        if isinstance(frame, str):
            continue  # status / advertise updates
        assert frame[0] == MESSAGE_DATA, frame[:1]
        sub_id, stamp = struct.unpack_from("<IQ", frame, 1)
        assert stamp > 0
        latest[channels[sub_id]] = json.loads(frame[13:])
        if want(latest):
            return latest
    raise AssertionError(f"not seen within {timeout} s; last: {latest}")


@pytest.mark.timeout(60)
def test_a_foxglove_client_sees_both_arms_and_the_learner(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"iterations": 30}))
    (run / "metrics.json").write_text(json.dumps(METRICS))
    domain, port = allocate_domain_id(), _free_port()
    view = RosProcess(["-m", "nf_bringup.fleet_view", "--ros-args", "-p", f"port:={port}",
                       "-p", f"run_dir:={run}"], domain, log_path=tmp_path / "fleet_view.log")
    arms = FakeArms(domain)
    try:
        _wait_for_server(port, [view], timeout=15)
        with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=5) as ws:
            assert ws.subprotocol in SUBPROTOCOLS
            channels: dict[int, str] = {}
            while len(channels) < 2:
                op = json.loads(ws.recv(timeout=5))
                if op["op"] == "advertise":
                    channels.update({c["id"]: c["topic"] for c in op["channels"]
                                     if c["topic"] in ("/fleet/arms", "/fleet/learner")})
            assert sorted(channels.values()) == ["/fleet/arms", "/fleet/learner"]
            # subscription id = channel id, so a frame names its channel
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c, "channelId": c} for c in channels]}))

            def seen(latest: dict[str, dict]) -> bool:
                by_arm = {a["arm"]: a for a in latest.get("/fleet/arms", {}).get("arms", [])}
                return ("/fleet/learner" in latest and {"/arm0", "/arm1"} <= set(by_arm)
                        and all(by_arm[a]["episodes"] >= 2 for a in ("/arm0", "/arm1")))

            latest = _read_until(ws, channels, seen, timeout=15)
        by_arm = {a["arm"]: a for a in latest["/fleet/arms"]["arms"]}
        assert by_arm["/arm0"]["mode"] == "running" and by_arm["/arm0"]["fault"] == ""
        assert by_arm["/arm1"]["mode"] == "safe_hold" and by_arm["/arm1"]["fault"] == "torque limit"
        for a in by_arm.values():
            assert a["alive"] and a["policy_version"] == 7 and a["lyapunov"] == 0.5
        assert by_arm["/arm0"]["success_rate"] == 1.0 and by_arm["/arm1"]["success_rate"] == 0.0
        learner = latest["/fleet/learner"]
        assert learner["iteration"] == 2 and learner["iterations"] == 30 and learner["success_rate"] == 0.5
        assert Path(learner["run"]) == run
    finally:
        arms.close()
        assert view.stop() == 0, view.log()
    assert "127.0.0.1" in view.log()


# ---------------------------------------------------------------- the cell: robot_state's description and transforms
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


class JointStates(PublisherThread):
    """This test's driver: the arm's joint states at 50 Hz, joint 1 turning slowly."""

    def __init__(self, domain: int) -> None:
        super().__init__(domain, "test_driver")
        self.pub = self.node.create_publisher(JointState, "joint_states", qos.STATE)
        self.thread.start()

    def _run(self) -> None:
        t = 0.0
        while not self.stop.wait(0.02):
            t += 0.02
            msg = JointState(name=list(panda_spec.JOINT_NAMES), position=list(Q + [0.2 * np.sin(t), 0, 0, 0, 0, 0, 0]))
            msg.header.stamp = self.node.get_clock().now().to_msg()
            self.pub.publish(msg)


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
        _wait_for_server(port, [view, state], timeout=20)
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
        deadline = time.monotonic() + 20  # the recorder subscribes once it has seen each topic; then 1 s of /tf
        while not all(f"recording {t} (" in recorder.log() for t in ("/tf", "/robot_description")):
            assert time.monotonic() < deadline, recorder.log()
            time.sleep(0.1)
        time.sleep(1.0)
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
    assert counts.get("/robot_description") == 1 and counts.get("/tf", 0) >= 10, counts  # 30 Hz
    assert schemas == {"/robot_description": "std_msgs/msg/String", "/tf": "tf2_msgs/msg/TFMessage"}, schemas
