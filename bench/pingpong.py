"""The floor of a lockstep loop in this runtime: two processes bounce a 7-value
Float64MultiArray back and forth over rclpy + DDS (same executor and QoS as the nodes), with no
work in between. A lockstep step is one such round trip plus the sim step and the controller.

``python bench/pingpong.py --seconds 5`` starts the echo side itself (role ``echo``, same
ROS_DOMAIN_ID, loopback only) and prints JSON: round trips per second, median and p99 (us).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import rclpy
import sources  # noqa: F401  (the package sources first on sys.path)
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from nf_bringup.processes import RosProcess, allocate_domain_id, isolate

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def serve(seconds: float) -> None:
    """Echo side: answer every ``ping`` with a ``pong`` for ``seconds``."""
    rclpy.init()
    node = rclpy.create_node("pingpong_echo")
    pub = node.create_publisher(Float64MultiArray, "pong", QOS)
    node.create_subscription(Float64MultiArray, "ping", pub.publish, QOS)
    executor = EventsExecutor()
    executor.add_node(node)
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
    except (ExternalShutdownException, KeyboardInterrupt):  # stopped by the pinging side
        pass
    node.destroy_node()
    rclpy.try_shutdown()


def measure(seconds: float, warmup: float = 1.0) -> dict:
    """Pinging side: start the echo process, bounce for ``seconds`` after ``warmup``, return stats."""
    domain = int(os.environ.get("ROS_DOMAIN_ID") or allocate_domain_id())  # the caller's, else its own
    isolate(os.environ, domain, sources=False)  # this side as the echo side: loopback, UDP
    echo = RosProcess([__file__, "--role", "echo", "--seconds", str(seconds + warmup + 8)], domain)
    rclpy.init()
    try:
        node = rclpy.create_node("pingpong")
        pub = node.create_publisher(Float64MultiArray, "ping", QOS)
        msg = Float64MultiArray(data=[0.0] * 7)
        times: list[float] = []
        sent = [0.0]

        def on_pong(_: Float64MultiArray) -> None:
            now = time.perf_counter()
            times.append(now - sent[0])
            sent[0] = time.perf_counter()
            pub.publish(msg)

        node.create_subscription(Float64MultiArray, "pong", on_pong, QOS)
        executor = EventsExecutor()
        executor.add_node(node)
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 or node.count_publishers("pong") == 0:
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError("the echo process did not appear within 20 s")
        start = time.monotonic()
        while time.monotonic() - start < warmup + seconds:
            if time.perf_counter() - sent[0] > 0.2:  # (re)start the ball: first ping, or a lost one
                sent[0] = time.perf_counter()
                pub.publish(msg)
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() - start < warmup:
                times.clear()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
        echo.stop()
    rt = np.asarray(times) * 1e6
    return {"round_trips_per_s": rt.size / seconds, "median_us": float(np.median(rt)),
            "p99_us": float(np.percentile(rt, 99)), "round_trips": int(rt.size)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--role", choices=("ping", "echo"), default="ping")
    args = parser.parse_args()
    if args.role == "echo":
        serve(args.seconds)
    else:
        print(json.dumps(measure(args.seconds)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
