"""Every nf_msgs interface crosses real DDS between two processes intact."""

from __future__ import annotations

import time

import pytest
import rclpy
from nf_msgs.action import RunEpisode
from nf_msgs.srv import ResetSim
from rclpy.action import ActionClient
from rclpy.executors import SingleThreadedExecutor
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
from ros_testing import REPO, RosProcess, allocate_domain_id

pytestmark = pytest.mark.ros


def _spin_until(executor, predicate, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and not predicate():
        executor.spin_once(timeout_sec=0.05)
    return predicate()


def test_every_interface_round_trips_between_processes(tmp_path):
    domain = allocate_domain_id()
    with RosProcess([str(REPO / "tests/peers/interface_peer.py")], domain, tmp_path / "peer.log") as peer:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        try:
            node = rclpy.create_node("interface_checker", context=ctx)
            executor = SingleThreadedExecutor(context=ctx)
            executor.add_node(node)
            qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
            received: dict[str, object] = {}
            for topic, make in TOPIC_SAMPLES.items():
                node.create_subscription(type(make()), topic, lambda m, t=topic: received.setdefault(t, m), qos)
            # clients first: Fast DDS drops a response to a reader the server has not matched within 100 ms
            client = node.create_client(ResetSim, "/test/reset")
            action = ActionClient(node, RunEpisode, "/test/run_episode")
            assert _spin_until(executor, lambda: len(received) == len(TOPIC_SAMPLES), 30.0), (
                f"received only {sorted(received)}; peer log:\n{peer.log()}")
            for topic, make in TOPIC_SAMPLES.items():
                assert differences(received[topic], make()) == [], topic

            # Service: the peer checks the request, we check the response.
            assert client.wait_for_service(timeout_sec=20.0)
            future = client.call_async(reset_request())
            assert _spin_until(executor, future.done, 20.0)
            assert differences(future.result(), reset_response()) == []

            # Action: goal checked by the peer, feedback and result checked here.
            assert action.wait_for_server(timeout_sec=20.0)
            feedback: list = []
            goal_future = action.send_goal_async(episode_goal(), feedback_callback=feedback.append)
            assert _spin_until(executor, goal_future.done, 20.0)
            handle = goal_future.result()
            assert handle.accepted
            result_future = handle.get_result_async()
            assert _spin_until(executor, result_future.done, 20.0)
            assert differences(result_future.result().result, episode_result()) == []
            assert feedback, "no action feedback arrived"
            assert differences(feedback[0].feedback, episode_feedback()) == []
            executor.shutdown()
            node.destroy_node()
        finally:
            rclpy.shutdown(context=ctx)
        assert peer.alive(), f"peer died:\n{peer.log()}"
    assert peer.proc.returncode in (0, -2), peer.log()
