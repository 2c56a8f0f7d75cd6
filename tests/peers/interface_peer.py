"""Peer process for the interface round-trip test: publishes every sample message, serves the
reset service and the episode action, each returning the shared samples."""

from __future__ import annotations

import time

import rclpy
from nf_msgs.action import RunEpisode
from nf_msgs.srv import ResetSim
from rclpy.action import ActionServer
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from interface_samples import (
    TOPIC_SAMPLES,
    differences,
    episode_feedback,
    episode_goal,
    episode_result,
    reset_request,
    reset_response,
)


class InterfacePeer(Node):
    def __init__(self) -> None:
        super().__init__("interface_peer")
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._pubs = []
        for topic, make in TOPIC_SAMPLES.items():
            msg = make()
            pub = self.create_publisher(type(msg), topic, qos)
            pub.publish(msg)
            self._pubs.append(pub)
        self.create_service(ResetSim, "/test/reset", self._on_reset)
        ActionServer(self, RunEpisode, "/test/run_episode", self._on_goal)

    def _on_reset(self, request: ResetSim.Request, response: ResetSim.Response) -> ResetSim.Response:
        bad = differences(request, reset_request())
        out = reset_response()
        if bad:  # tell the caller what arrived damaged
            out.success, out.message = False, "; ".join(bad)
        return out

    def _on_goal(self, handle) -> RunEpisode.Result:
        bad = differences(handle.request, episode_goal())
        for _ in range(10):  # the client may attach its feedback callback a little after acceptance
            handle.publish_feedback(episode_feedback())
            time.sleep(0.05)
        handle.succeed()
        result = episode_result()
        if bad:
            result.completed, result.message = False, "; ".join(bad)
        return result


def main() -> None:
    rclpy.init()
    try:
        rclpy.spin(InterfacePeer())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
