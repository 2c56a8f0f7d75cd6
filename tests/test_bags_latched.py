"""The recorder takes every latched (transient-local) message it is asked to record, including one
published before it started (issue 16, item 14): a real publisher process publishes the policy
with the learner's QoS and lingers, then the recorder starts. Also when a volatile publisher of
the same topic is around (the recorder subscribes volatile to match it, and takes the latched
history with a second, transient-local subscription), and when the latched publisher joins after
the recorder subscribed to a volatile one.

ROS domains: ``bag_domain_id`` (also used by tests/test_bags.py) takes them from
``NF_TEST_DOMAINS=first-last`` when set (a shared machine gives each engineer a range), else from
``ros_testing.allocate_domain_id``."""

from __future__ import annotations

import itertools
import os
import time
from pathlib import Path

import pytest
from nf_bags import bagfile

from ros_testing import RosProcess, allocate_domain_id

pytestmark = pytest.mark.ros

_counter = itertools.count()

# a publisher of /policy_parameters: argv[1] transient_local|volatile, argv[2] version, argv[3] s to linger
PUBLISHER = """
import sys, time, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy
from nf_msgs.msg import PolicyParameters
rclpy.init()
node = rclpy.create_node("policy_source_" + sys.argv[2])
durability = DurabilityPolicy.TRANSIENT_LOCAL if sys.argv[1] == "transient_local" else DurabilityPolicy.VOLATILE
pub = node.create_publisher(PolicyParameters, "/policy_parameters",
                            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=durability))
msg = PolicyParameters()
msg.version = int(sys.argv[2])
msg.weights = [0.5 * msg.version] * 100
pub.publish(msg)
print("published", msg.version, flush=True)
end = time.monotonic() + float(sys.argv[3])
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
"""


def bag_domain_id() -> int:
    """A ROS_DOMAIN_ID for one bag test: from ``NF_TEST_DOMAINS`` (e.g. ``60-69``) when set."""
    spec = os.environ.get("NF_TEST_DOMAINS", "")
    if not spec:
        return allocate_domain_id()
    first, last = (int(x) for x in spec.split("-"))
    return first + (os.getpid() + next(_counter)) % (last - first + 1)


def _wait(predicate, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def _versions(bag: Path) -> list[int]:
    """Policy versions in the bag (also while it is being recorded: its complete chunks)."""
    from nf_bags import reader

    try:
        return [int(p.version) for p in reader.policies(bag)]
    except bagfile.BagError:  # not created yet
        return []


def _publisher(durability: str, version: int, domain: int, tmp: Path, linger: float = 60.0) -> RosProcess:
    proc = RosProcess(["-c", PUBLISHER, durability, str(version), str(linger)], domain, tmp / f"pub{version}.log")
    assert _wait(lambda: "published" in proc.log() or not proc.alive(), 60), proc.log()
    return proc


def _record(bag: Path, domain: int, tmp: Path, *args: str) -> RosProcess:
    return RosProcess(["-m", "nf_bags.record", "-o", str(bag), *args], domain, tmp / "recorder.log")


def _recording(rec: RosProcess, topic: str = "/policy_parameters", timeout: float = 60.0) -> None:
    assert _wait(lambda: f"recording {topic} (" in rec.log(), timeout), rec.log()


@pytest.mark.parametrize("mode", ["topics", "all"])
def test_a_policy_latched_before_the_recorder_started_is_in_the_bag(tmp_path, mode):
    domain = bag_domain_id()
    bag = tmp_path / "bag"
    pub = _publisher("transient_local", 3, domain, tmp_path)
    try:
        rec = _record(bag, domain, tmp_path, *(["--topics", "/policy_parameters"] if mode == "topics" else []))
        try:
            _recording(rec)
            _wait(lambda: _versions(bag) == [3], 30)  # history comes on matching, in the next chunk (1 s)
        finally:
            assert rec.stop() == 0, rec.log()
    finally:
        pub.stop()
    health = bagfile.scan(bag)
    assert health.closed and _versions(bag) == [3], (rec.log(), dict(health.counts))


def test_a_latched_policy_is_taken_when_a_volatile_publisher_shares_the_topic(tmp_path):
    """Before: "transient local if all publishers are" made the subscription volatile, and the latched
    policy published before the recorder matched was never recorded."""
    domain = bag_domain_id()
    bag = tmp_path / "bag"
    latched = _publisher("transient_local", 4, domain, tmp_path)
    volatile = _publisher("volatile", 5, domain, tmp_path)
    try:
        rec = _record(bag, domain, tmp_path, "--topics", "/policy_parameters")
        try:
            _recording(rec)
            # the recorder may see the volatile publisher first: the latched one is taken once it is seen
            _wait(lambda: _versions(bag) == [4], 30)
        finally:
            assert rec.stop() == 0, rec.log()
    finally:
        latched.stop()
        volatile.stop()
    assert _versions(bag) == [4], rec.log()  # 5 was published (volatile) before the recorder: gone


def test_a_latched_publisher_joining_after_a_volatile_one_left_is_taken(tmp_path):
    """The recorder subscribed (volatile) to a volatile publisher; that one leaves and a latched one
    joins, having published before it was matched: the recorder follows the publishers' QoS."""
    domain = bag_domain_id()
    bag = tmp_path / "bag"
    volatile = _publisher("volatile", 1, domain, tmp_path, linger=60.0)
    rec = _record(bag, domain, tmp_path, "--topics", "/policy_parameters")
    try:
        _recording(rec)
        volatile.stop()
        _wait(lambda: False, 1.0)
        latched = _publisher("transient_local", 2, domain, tmp_path)
        try:
            assert _wait(lambda: "publishers changed" in rec.log(), 30), rec.log()
            _wait(lambda: _versions(bag) == [2], 30)
        finally:
            latched.stop()
    finally:
        assert rec.stop() == 0, rec.log()
    assert _versions(bag) == [2], rec.log()
