"""RunEpisode goals that cannot start, over real DDS against a standalone nf_controller with no
simulator: the policy version never arrives (aborted after ``policy_wait``), a cancel while the goal
waits for it (canceled at once), and a reset service that does not exist (aborted after the
service wait). The set-up runs on a timer, without a coroutine (``NFControllerNode._on_accepted``):
these are its failure paths."""

from __future__ import annotations

import time

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from nf_msgs.action import RunEpisode
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.action import ActionClient

from nf_core import qos
from nf_core.topics import POLICY_PARAMETERS

from ros_testing import RosProcess, allocate_domain_id
from test_nodes import Probe, policy_msg

pytestmark = pytest.mark.ros


def _send(probe: Probe, client: ActionClient, version: int) -> object:
    sent = client.send_goal_async(RunEpisode.Goal(policy_version=version, seed=-1, noise_seed=1, duration=0.5))
    assert probe.spin_until(sent.done, 10) and sent.result().accepted
    return sent.result()


def _result(probe: Probe, handle: object, timeout: float) -> tuple[int, RunEpisode.Result]:
    done = handle.get_result_async()
    assert probe.spin_until(done.done, timeout)
    return done.result().status, done.result().result


def test_goals_that_cannot_start_end_with_the_reason(tmp_path):
    domain = allocate_domain_id()
    probe = Probe(domain)
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "policy_wait:=1.0",
                      "-p", "reset_service:=/nowhere/reset"], domain, tmp_path / "controller.log")
    try:
        client = ActionClient(probe.node, RunEpisode, "run_episode")
        assert client.wait_for_server(timeout_sec=30), ctl.log()
        # no policy at all: the goal waits policy_wait (1 s), then is aborted with the reason
        t0 = time.monotonic()
        status, result = _result(probe, _send(probe, client, 9), 20)
        waited = time.monotonic() - t0
        assert status == GoalStatus.STATUS_ABORTED and not result.completed
        assert "controller has policy version" in result.message and "asks for 9" in result.message, result.message
        assert 0.9 < waited < 10.0, waited
        # canceled while it waits for its policy: canceled at once, and the next goal is accepted
        handle = _send(probe, client, 9)
        cancel = handle.cancel_goal_async()
        assert probe.spin_until(cancel.done, 10)
        status, result = _result(probe, handle, 10)
        assert status == GoalStatus.STATUS_CANCELED and result.message == "canceled", result.message
        # the policy arrives, but the reset service does not exist: aborted after the service wait
        pub = probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
        pub.publish(policy_msg(np.array([0.5, 0.0, 0.3]), version=9))
        status, result = _result(probe, _send(probe, client, 9), 30)
        assert status == GoalStatus.STATUS_ABORTED
        assert result.message == "reset service /nowhere/reset not available", result.message
        assert ctl.alive(), ctl.log()
    finally:
        ctl.stop()
        probe.close()
