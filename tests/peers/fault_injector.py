"""Peer process for the controller's bad-input test: publishes joint states on ``joint_states``,
first valid ones, then a cycle of malformed ones (NaN, Inf, wrong sizes, unknown and missing
names, an out-of-order stamp), then valid ones again, and exits.

Usage: fault_injector.py VALID_S BAD_S AFTER_S  (seconds of each phase; 500 states/s)
"""

from __future__ import annotations

import sys
import time

import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

NAMES = [f"panda_joint{i}" for i in range(1, 8)]
Q0 = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])  # the gear scene's start pose
PERIOD = 0.002  # s


def _bad_states(q: np.ndarray) -> list[tuple[str, list[str], list[float], list[float]]]:
    nan_q, inf_dq = q.copy(), np.zeros(7)
    nan_q[2], inf_dq[5] = np.nan, np.inf
    return [
        ("nan_position", NAMES, nan_q.tolist(), [0.0] * 7),
        ("inf_velocity", NAMES, q.tolist(), inf_dq.tolist()),
        ("short_position", NAMES, q[:6].tolist(), [0.0] * 7),
        ("unknown_name", [*NAMES[:6], "elbow_joint"], q.tolist(), [0.0] * 7),
        ("missing_name", NAMES[:6], q[:6].tolist(), [0.0] * 6),
        ("finger_extra", [*NAMES, "panda_finger_joint1"], [*q.tolist(), 0.0], [0.0] * 8),
        ("out_of_order", NAMES, q.tolist(), [0.0] * 7),
    ]


def main() -> None:
    valid_s, bad_s, after_s = (float(a) for a in sys.argv[1:4])
    rclpy.init()
    node = rclpy.create_node("fault_injector")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(JointState, "joint_states", qos)
    deadline = time.monotonic() + 20.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:  # discovery
        time.sleep(0.01)
    print(f"controller matched after {time.monotonic() - deadline + 20.0:.2f} s", flush=True)
    stamp_ns = 10**9
    n = 0
    out_of_order = 0

    def send(names: list[str], q: list[float], dq: list[float], stamp: int) -> None:
        msg = JointState(name=names, position=q, velocity=dq)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        pub.publish(msg)

    try:
        for phase, duration in (("valid", valid_s), ("bad", bad_s), ("valid", after_s)):
            end = time.monotonic() + duration
            bad = _bad_states(Q0)
            while time.monotonic() < end:
                stamp_ns += 1_000_000
                if phase == "bad" and n % 2:  # every other state is bad, cycling through the kinds
                    kind, names, q, dq = bad[(n // 2) % len(bad)]
                    out_of_order += kind == "out_of_order"
                    send(names, q, dq, stamp_ns - 50_000_000 if kind == "out_of_order" else stamp_ns)
                else:
                    send(NAMES, Q0.tolist(), [0.0] * 7, stamp_ns)
                n += 1
                time.sleep(PERIOD)
            print(f"phase {phase} done after {n} states ({out_of_order} out of order)", flush=True)
        t_ack = time.monotonic()
        acked = pub.wait_for_all_acked(Duration(seconds=5))
        print(f"all acknowledged: {acked} after {time.monotonic() - t_ack:.2f} s", flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
