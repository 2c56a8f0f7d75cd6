"""``fleet_view``: a live view of the fleet on a Foxglove WebSocket (ws://127.0.0.1:8765).

Finds every arm (each namespace that publishes ``<ns>/controller_status``, the root one too),
follows its controller status and rollout chunks, reads the learner's progress from its run
folder, and serves two JSON channels to Foxglove (Studio or app: "Open connection"):

- ``/fleet/arms`` (5 Hz, and at once when an arm's mode, fault, policy or episode changes): per arm
  its mode, fault, policy version, episode, V and dV/dt, and its success rate over its last episodes;
- ``/fleet/learner`` (when its files change): iteration of iterations, success, time per iteration;
- per arm that has a ``robot_state`` node, its ``<ns>/robot_description`` (JSON ``{"data": URDF}``, again
  every few seconds for clients that connect later: the 3D panel's URDF layer, source "topic") and its
  ``<ns>/tf`` as ``foxglove.FrameTransforms`` (an arm under a namespace gets its frames prefixed
  ``<ns>/``, the URDF layer's frame prefix, so that arms do not share frames).

    fleet_view --ros-args -p run_dir:=runs -p port:=8765

The server binds 127.0.0.1 only: from another machine, forward the port (``ssh -L 8765:localhost:8765``).
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any

import foxglove
import foxglove.channels
import foxglove.messages
from nf_msgs.msg import ControllerStatus, RolloutChunk
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from nf_bringup.fleet_state import FleetState, LearnerProgress
from nf_bringup.robot_state import DESCRIPTION, DESCRIPTION_QOS, TF_QOS
from nf_core import qos
from nf_core.ros_runtime import declare_read_only, run_node
from nf_core.topics import CONTROLLER_STATUS, ROLLOUTS
from tf2_msgs.msg import TFMessage

LOG = logging.getLogger("fleet_view")
HOST = "127.0.0.1"  # never another interface: the view has no authentication
STATUS_TYPE = "nf_msgs/msg/ControllerStatus"
DESCRIPTION_SCHEMA = {"type": "object", "properties": {"data": {"type": "string"}}}
DESCRIPTION_PERIOD = 2.0  # s between repeats of each arm's robot description
# A monitor must not hold back the controller's writer: best effort, the latest few statuses only.
STATUS_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)

PARAMETERS: dict[str, tuple[Any, str]] = {
    "port": (8765, "WebSocket port on 127.0.0.1 (0: any free port, printed at start)"),
    "run_dir": ("runs", "the learner's out_dir, a run folder, or a folder of runs (the newest is followed)"),
    "success_depth": (0.016, "insertion depth [m] that makes an episode a success (gear: 0.016, peg: 0.025)"),
    "publish_rate": (5.0, "/fleet/arms messages per s"),
    "discovery_period": (1.0, "s between looks for new arms"),
    "rollouts": (True, "follow <ns>/rollouts for each arm's success rate (whole chunks cross DDS)"),
}

ARMS_SCHEMA = {
    "type": "object",
    "properties": {
        "count": {"type": "integer"},
        "arms": {"type": "array", "items": {"type": "object", "properties": {
            "arm": {"type": "string"}, "alive": {"type": "boolean"}, "mode": {"type": "string"},
            "fault": {"type": "string"}, "policy_version": {"type": "integer"}, "episode_id": {"type": "integer"},
            "episode_time": {"type": ["number", "null"]}, "lyapunov": {"type": ["number", "null"]},
            "lyapunov_rate": {"type": ["number", "null"]}, "torque_norm": {"type": ["number", "null"]},
            "deadline_misses": {"type": "integer"}, "episodes": {"type": "integer"},
            "success_rate": {"type": ["number", "null"]}, "success_window": {"type": "integer"},
            "last_success": {"type": ["boolean", "null"]}, "last_depth": {"type": ["number", "null"]},
            "status_age": {"type": ["number", "null"]}}}},
    },
}
LEARNER_SCHEMA = {
    "type": "object",
    "properties": {
        "run": {"type": "string"}, "iteration": {"type": "integer"}, "iterations": {"type": ["integer", "null"]},
        "success_rate": {"type": ["number", "null"]}, "return_mean": {"type": ["number", "null"]},
        "final_distance_mean": {"type": ["number", "null"]},
        "seconds_per_iteration": {"type": ["number", "null"]},
        "mean_seconds_per_iteration": {"type": ["number", "null"]}, "seconds_left": {"type": ["number", "null"]},
        "arms_used": {"type": ["number", "null"]}, "rerun_episodes": {"type": ["number", "null"]},
        "dropped_episodes": {"type": ["number", "null"]},
        "success_history": {"type": "array", "items": {"type": ["number", "null"]}},
        "rollouts_per_arm": {"type": "object"},
    },
}


class FleetViewNode(Node):
    """Subscribes to every arm it finds and serves the fleet's state on a Foxglove WebSocket."""

    def __init__(self) -> None:
        super().__init__("fleet_view")
        self.settings = declare_read_only(self, PARAMETERS)
        self.fleet = FleetState(float(self.settings["success_depth"]))
        self.learner = LearnerProgress(Path(self.settings["run_dir"]))
        self._subscribed: set[str] = set()  # namespaces ("" for the root) already followed
        self._described: set[str] = set()  # namespaces whose robot_state is followed
        self._descriptions: dict[str, tuple[Any, str]] = {}  # ns -> (channel, URDF)
        self._tf_channels: dict[str, Any] = {}
        self.server = foxglove.start_server(name="nf-control fleet", host=HOST, port=int(self.settings["port"]))
        self.arms_channel = foxglove.Channel("/fleet/arms", schema=ARMS_SCHEMA)
        self.learner_channel = foxglove.Channel("/fleet/learner", schema=LEARNER_SCHEMA)
        LOG.info("serving ws://%s:%d (Foxglove: Open connection); learner files under %s",
                 HOST, self.server.port, self.settings["run_dir"])
        self._discover()
        self.create_timer(float(self.settings["discovery_period"]), self._discover)
        self.create_timer(1.0 / float(self.settings["publish_rate"]), self._publish_arms)
        self.create_timer(1.0, self._publish_learner)
        self.create_timer(DESCRIPTION_PERIOD, self._publish_descriptions)

    def _discover(self) -> None:
        """Follow every namespace that publishes a ControllerStatus and is not followed yet, and every
        robot_state's description and transforms."""
        topics = self.get_topic_names_and_types()
        self._discover_cells(topics)
        suffix = "/" + CONTROLLER_STATUS
        for name, types in topics:
            if not name.endswith(suffix) or STATUS_TYPE not in types:
                continue
            ns = name[:-len(suffix)]
            if ns in self._subscribed:
                continue
            self._subscribed.add(ns)
            self.create_subscription(ControllerStatus, f"{ns}/{CONTROLLER_STATUS}",
                                     lambda msg, ns=ns: self._on_status(ns, msg), STATUS_QOS)
            if self.settings["rollouts"]:
                self.create_subscription(RolloutChunk, f"{ns}/{ROLLOUTS}",
                                         lambda msg, ns=ns: self._on_chunk(ns, msg), qos.ROLLOUTS)
            LOG.info("following arm %s", ns or "/")

    def _discover_cells(self, topics: list[tuple[str, list[str]]]) -> None:
        suffix = "/" + DESCRIPTION
        for name, types in topics:
            ns = name[:-len(suffix)]
            if not name.endswith(suffix) or "std_msgs/msg/String" not in types or ns in self._described:
                continue
            self._described.add(ns)
            self._tf_channels[ns] = foxglove.channels.FrameTransformsChannel(f"{ns}/tf")
            self._descriptions[ns] = (foxglove.Channel(f"{ns}/{DESCRIPTION}", schema=DESCRIPTION_SCHEMA), "")
            self.create_subscription(String, name, lambda msg, ns=ns: self._on_description(ns, msg), DESCRIPTION_QOS)
            self.create_subscription(TFMessage, f"{ns}/tf", lambda msg, ns=ns: self._on_tf(ns, msg), TF_QOS)
            LOG.info("following the robot description and transforms of %s", ns or "/")

    def _on_description(self, ns: str, msg: String) -> None:
        channel = self._descriptions[ns][0]
        self._descriptions[ns] = (channel, msg.data)
        channel.log({"data": msg.data})

    def _publish_descriptions(self) -> None:
        for channel, urdf in self._descriptions.values():
            if urdf:
                channel.log({"data": urdf})

    def _on_tf(self, ns: str, msg: TFMessage) -> None:
        prefix = f"{ns.strip('/')}/" if ns else ""
        transforms = []
        for t in msg.transforms:
            tr, rot = t.transform.translation, t.transform.rotation
            transforms.append(foxglove.messages.FrameTransform(
                timestamp=foxglove.messages.Timestamp(sec=t.header.stamp.sec, nsec=t.header.stamp.nanosec),
                parent_frame_id=prefix + t.header.frame_id, child_frame_id=prefix + t.child_frame_id,
                translation=foxglove.messages.Vector3(x=tr.x, y=tr.y, z=tr.z),
                rotation=foxglove.messages.Quaternion(x=rot.x, y=rot.y, z=rot.z, w=rot.w)))
        self._tf_channels[ns].log(foxglove.messages.FrameTransforms(transforms=transforms))

    def _on_status(self, ns: str, msg: ControllerStatus) -> None:
        if self.fleet.status(ns, time.monotonic(), mode=msg.mode, fault=msg.fault,
                             policy_version=msg.policy_version, episode_id=msg.episode_id,
                             lyapunov=msg.lyapunov, lyapunov_rate=msg.lyapunov_rate,
                             torque_norm=msg.torque_norm, deadline_misses=msg.deadline_misses):
            self._publish_arms()

    def _on_chunk(self, ns: str, msg: RolloutChunk) -> None:
        if self.fleet.chunk(ns, episode_id=msg.episode_id, final=msg.final, t=msg.t,
                            insertion_depth=msg.insertion_depth):
            self._publish_arms()

    def _publish_arms(self) -> None:
        """The snapshot of every arm: on the timer, and at once on a change (a mode switch should not
        wait for the next tick; a burst of changes still costs one JSON per status at most)."""
        if self.fleet.arms:
            self.arms_channel.log(self.fleet.snapshot(time.monotonic()))

    def _publish_learner(self) -> None:
        message, _ = self.learner.poll()
        # again every second, not only on a change: a client that connects late gets it too
        if message is not None:
            self.learner_channel.log(message)

    def destroy_node(self) -> None:
        """Stop the WebSocket server with the node."""
        self.server.stop()
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    """Console script ``fleet_view``."""
    logging.basicConfig(level=logging.INFO, format="[fleet_view] %(message)s", stream=sys.stdout)
    return run_node(FleetViewNode, "fleet_view", __doc__.split("\n\n")[0], argv,
                    make_executor=SingleThreadedExecutor)


if __name__ == "__main__":
    raise SystemExit(main())
