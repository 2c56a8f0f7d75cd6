"""``fleet_view``: a live view of the fleet on a Foxglove WebSocket (ws://127.0.0.1:8765).

Finds every arm (each namespace that publishes ``<ns>/controller_status``, the root one too),
follows its controller status and rollout chunks, reads the learner's progress from its run
folder, and serves two JSON channels to Foxglove (Studio or app: "Open connection"):

- ``/fleet/arms`` (5 Hz, and at once when an arm's mode, fault, policy or episode changes): per arm
  its mode, fault, policy version, episode, V and dV/dt, and its success rate over its last episodes;
- ``/fleet/learner`` (when its files change): iteration of iterations, success, time per iteration.

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
from nf_msgs.msg import ControllerStatus, RolloutChunk
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from nf_bringup.fleet_state import FleetState, LearnerProgress
from nf_core import qos
from nf_core.ros_runtime import declare_read_only, run_node
from nf_core.topics import CONTROLLER_STATUS, ROLLOUTS

LOG = logging.getLogger("fleet_view")
HOST = "127.0.0.1"  # never another interface: the view has no authentication
STATUS_TYPE = "nf_msgs/msg/ControllerStatus"
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
        self.server = foxglove.start_server(name="nf-control fleet", host=HOST, port=int(self.settings["port"]))
        self.arms_channel = foxglove.Channel("/fleet/arms", schema=ARMS_SCHEMA)
        self.learner_channel = foxglove.Channel("/fleet/learner", schema=LEARNER_SCHEMA)
        LOG.info("serving ws://%s:%d (Foxglove: Open connection); learner files under %s",
                 HOST, self.server.port, self.settings["run_dir"])
        self._discover()
        self.create_timer(float(self.settings["discovery_period"]), self._discover)
        self.create_timer(1.0 / float(self.settings["publish_rate"]), self._publish_arms)
        self.create_timer(1.0, self._publish_learner)

    def _discover(self) -> None:
        """Follow every namespace that publishes a ControllerStatus and is not followed yet."""
        suffix = "/" + CONTROLLER_STATUS
        for name, types in self.get_topic_names_and_types():
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
