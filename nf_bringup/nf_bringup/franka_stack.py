"""``nf_franka_stack``: a Franka arm and the stable flow controller composed in one process.

Two ROS nodes, ``franka_driver`` and ``nf_controller``, with their own names and parameters, as
``nf_sim_stack`` composes the MuJoCo arm; the 1 kHz state -> torque call is a direct call from
libfranka's torque loop into the controller's core. The learner and the recorder talk to the
controller node exactly as in simulation.

    nf_franka_stack --ros-args --params-file config/franka.yaml -p franka_driver:robot_ip:=172.16.0.2

The driver connects and identifies the arm first; the controller is then built with that arm's
model and joint names, and the driver refuses to start with ``gravity_compensation`` on.
"""

from __future__ import annotations

import sys

from rclpy.node import Node

from franka_driver.node import FrankaDriverNode
from nf_controller_node.node import NFControllerNode
from nf_core.ros_runtime import freeze_heap, run_node

# GIL hand-over interval of the composed process (as nf_sim_stack): a busy executor thread must
# not keep the torque loop waiting for Python's default 5 ms.
SWITCH_INTERVAL = 1e-4


def make_nodes() -> list[Node]:
    """The robot's driver (connected, identified), then the controller with the robot's model."""
    driver = FrankaDriverNode()
    controller = NFControllerNode(composed=True, arm=driver.arm, joint_names=driver.joint_names)
    try:
        loop = driver.attach(controller)
    except ValueError:
        controller.destroy_node()
        driver.destroy_node()
        raise
    controller.attach_driver(loop)
    return [controller, driver]


def _start(nodes: list[Node]) -> None:
    freeze_heap()  # no full garbage collection of the start-up objects inside the 1 kHz loop
    for node in nodes:
        if isinstance(node, FrankaDriverNode):
            node.start_driver()


def main(args: list[str] | None = None) -> int:
    """Console script ``nf_franka_stack``."""
    sys.setswitchinterval(SWITCH_INTERVAL)
    return run_node(make_nodes, "nf_franka_stack", "A Franka arm (libfranka torque loop) and the stable flow "
                    "controller composed in one process (the 1 kHz tick is a direct call; both nodes keep their "
                    "ROS interfaces).", args, started=_start)


if __name__ == "__main__":
    raise SystemExit(main())
