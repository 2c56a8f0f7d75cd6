"""A minimal "hardware-like" arm driver for tests: a MuJoCo Panda stepped by a 1 kHz wall-clock
timer that speaks only the two ros2_control topics (``joint_states`` out, joint names in a
different order than the controller's; ``effort_controller/commands`` in) and adds gravity
itself, as Franka's driver does. ``effort`` reports the command it applies (default) or, with
``--effort measured``, the joint torque the arm applies, gravity included (franka_ros2's convention:
libfranka's tau_J). No reset service, no task status, no stamp handshake.

``SIGUSR1`` stops the state stream (and the next one resumes it) while the arm runs on under the
last command that came in, as when a driver's state path hangs; each switch logs one JSON line:
``{"joint_states": "off"|"on", "q": [...], "dq": [...], "command": [...], "zero_after": s}``
(panda_joint1..7 order, rad, rad/s, the command applied on top of gravity in Nm; when back on, the
wall time from off to the first tick whose command was all zero, null if none was).

Run: python tests/peers/hw_driver.py [--effort command|measured]   (stops on SIGINT)
"""

from __future__ import annotations

import json
import signal
import threading
import time

import mujoco
import numpy as np
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from sim_bridge_node.env import InsertionEnv

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
ORDER = [6, 0, 5, 1, 4, 2, 3]  # published joint order (a permutation of panda_joint1..7)


class HardwareLikeDriver(Node):
    def __init__(self, measured: bool = False) -> None:
        super().__init__("hw_driver")
        self.measured = measured  # effort = command + gravity (franka_ros2) instead of the command
        self.env = InsertionEnv("free")
        self.env.reset()
        self.names = [self.env.scene.joint_names[i] for i in ORDER]
        self.command = np.zeros(7)
        self.publishing = True  # joint_states go out (SIGUSR1 switches, see switch_states)
        self.switch_asked = False
        self._off_since = 0.0  # monotonic s when the states stopped
        self._zero_after: float | None = None  # s from then to the first all-zero command
        self._g_data = mujoco.MjData(self.env.model)
        m = self.env.model
        self._vadr = np.array([m.joint(n).dofadr[0] for n in self.env.scene.joint_names])
        self.pub = self.create_publisher(JointState, "joint_states", QOS)
        self.create_subscription(Float64MultiArray, "effort_controller/commands", self.on_command, QOS)
        self.create_timer(0.001, self.tick)

    def on_command(self, msg: Float64MultiArray) -> None:
        data = np.asarray(msg.data, dtype=float)
        if data.shape == (7,) and np.all(np.isfinite(data)):
            self.command = data

    def switch_states(self) -> None:
        """From the signal handler: stop (or resume) joint_states at the next tick."""
        self.switch_asked = True

    def tick(self) -> None:
        env = self.env
        now = time.monotonic()
        if self.switch_asked:
            self.switch_asked = False
            self.publishing = not self.publishing
            print(json.dumps({"joint_states": "on" if self.publishing else "off", "q": env.q.tolist(),
                              "dq": env.dq.tolist(), "command": self.command.tolist(),
                              "zero_after": self._zero_after if self.publishing else None}), flush=True)
            self._off_since, self._zero_after = now, None
        if not self.publishing and self._zero_after is None and not np.any(self.command):
            self._zero_after = now - self._off_since
        gravity = self._gravity()
        env.step(np.clip(self.command + gravity, -env.torque_limits, env.torque_limits))
        if not self.publishing:
            return
        msg = JointState()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.name = self.names
        msg.position = env.q[ORDER].tolist()
        msg.velocity = env.dq[ORDER].tolist()
        # measured: the joint torque at the state it reports, the gravity of that q included (tau_J)
        effort = self.command + self._gravity() if self.measured else self.command
        msg.effort = effort[ORDER].tolist()
        self.pub.publish(msg)

    def _gravity(self) -> np.ndarray:
        """g(q): the bias force at zero velocity."""
        d = self._g_data
        d.qpos[:] = self.env.data.qpos
        mujoco.mj_forward(self.env.model, d)
        return d.qfrc_bias[self._vadr]


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--effort", choices=("command", "measured"), default="command")
    args, _ = ap.parse_known_args()
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = HardwareLikeDriver(measured=args.effort == "measured")
    signal.signal(signal.SIGUSR1, lambda *_: node.switch_states())
    ex = EventsExecutor()
    ex.add_node(node)
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.1)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
