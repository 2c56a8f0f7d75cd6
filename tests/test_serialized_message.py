"""SerializedMessage: messages serialized once and rewritten in place read back (with rclpy's own
deserializer) exactly as the typed messages would."""

from __future__ import annotations

import numpy as np
import pytest
from nf_msgs.msg import TaskStatus
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from nf_core.serialized_message import SerializedMessage
from nf_core.topics import parse_stamp_label, stamp_label

NAMES = [f"panda_joint{i}" for i in range(1, 8)]


def test_joint_state_rewritten_in_place_reads_back_as_the_typed_message():
    msg = JointState(name=NAMES, position=[0.0] * 7, velocity=[0.0] * 7, effort=[0.0] * 7)
    msg.header.frame_id = "base"
    raw = SerializedMessage(msg, floats=("position", "velocity", "effort"), stamp="header.stamp")
    assert raw.payload() == serialize_message(msg)  # built from msg's own values, not the sentinels
    rng = np.random.default_rng(0)
    for stamp_ns in (0, 1_000_000, 123_456_789_012_345):
        q, dq, tau = rng.normal(size=(3, 7))
        raw.floats["position"][:], raw.floats["velocity"][:], raw.floats["effort"][:] = q, dq, tau
        raw.set_stamp(stamp_ns)
        back = deserialize_message(raw.payload(), JointState)
        assert back.name == NAMES and back.header.frame_id == "base"
        assert back.header.stamp.sec * 1_000_000_000 + back.header.stamp.nanosec == stamp_ns
        np.testing.assert_array_equal(back.position, q)
        np.testing.assert_array_equal(back.velocity, dq)
        np.testing.assert_array_equal(back.effort, tau)


def test_command_label_clock_and_task_status():
    cmd = Float64MultiArray(data=[0.0] * 7)
    cmd.layout.dim = [MultiArrayDimension(label=stamp_label(0), size=7, stride=7)]
    raw = SerializedMessage(cmd, floats=("data",), texts=("layout.dim.0.label",))
    raw.set_text("layout.dim.0.label", stamp_label(987_654_321_000))
    raw.floats["data"][:] = np.arange(7.0)
    back = deserialize_message(raw.payload(), Float64MultiArray)
    assert parse_stamp_label(back.layout.dim[0].label) == 987_654_321_000
    assert back.layout.dim[0].size == 7 and list(back.data) == list(np.arange(7.0))
    with pytest.raises(ValueError, match="holds"):
        raw.set_text("layout.dim.0.label", "state_stamp_ns=1")  # another length would shift the bytes after it

    clock = SerializedMessage(Clock(), stamp="clock")
    clock.set_stamp(5_000_000_007)
    back = deserialize_message(clock.payload(), Clock)
    assert (back.clock.sec, back.clock.nanosec) == (5, 7)

    task = TaskStatus(task="gear", part_position=[0.0, 0.0, 0.0])
    raw = SerializedMessage(task, floats=("insertion_depth", "contact_force", "part_position"), bools=("success",),
                            stamp="header.stamp")
    for success in (True, False):
        raw.floats["insertion_depth"][0] = 0.0175
        raw.floats["contact_force"][0] = 3.5
        raw.floats["part_position"][:] = [0.5, 0.0, 0.07]
        raw.set_bool("success", success)
        raw.set_stamp(2_500_000_000)
        back = deserialize_message(raw.payload(), TaskStatus)
        assert back.task == "gear" and back.success is success
        assert (back.insertion_depth, back.contact_force, list(back.part_position)) == (0.0175, 3.5, [0.5, 0.0, 0.07])
        assert (back.header.stamp.sec, back.header.stamp.nanosec) == (2, 500_000_000)


def test_the_payload_is_a_copy():
    raw = SerializedMessage(Clock(), stamp="clock")
    first = raw.payload()
    raw.set_stamp(1)
    assert first != raw.payload()
