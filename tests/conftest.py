"""Shared pytest setup: every ROS context in the test process stays on loopback."""

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_STATIC_PEERS", None)
os.environ["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"  # see ros_testing.TEST_TRANSPORTS
