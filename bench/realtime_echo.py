"""Baseline responder for bench_realtime: answers every joint state with a zero effort command.

Same runtime as nf_controller (``run_node``: EventsExecutor, one node) but no controller work,
so the latency it sees is the floor set by rclpy and DDS on this machine. Run the sim with
``driver_gravity_compensation:=true`` so a zero command holds the arm.
"""

from __future__ import annotations

import array
import time

from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from nf_core import qos, topics
from nf_core.ros_runtime import run_node


class EchoNode(Node):
    """Zero command labelled with the stamp of the state it answers."""

    def __init__(self) -> None:
        super().__init__("realtime_echo")
        self._cmd = Float64MultiArray()
        self._dim = MultiArrayDimension(size=7, stride=7)
        self._cmd.layout.dim = [self._dim]
        self._zero = array.array("d", bytes(8 * 7))
        self._pub = self.create_publisher(Float64MultiArray, topics.COMMANDS, qos.STATE)
        self.create_subscription(JointState, topics.JOINT_STATES, self._on_state, qos.STATE)
        self.latest = 0.0

    def _on_state(self, msg: JointState) -> None:
        stamp = msg.header.stamp
        self._dim.label = topics.stamp_label(stamp.sec * 1_000_000_000 + stamp.nanosec)
        self._cmd.data = self._zero
        self._pub.publish(self._cmd)
        self.latest = time.monotonic()


if __name__ == "__main__":
    raise SystemExit(run_node(EchoNode, "realtime_echo", __doc__.splitlines()[0]))
