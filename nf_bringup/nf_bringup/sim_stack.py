"""``nf_sim_stack``: the MuJoCo arm and the flow controller composed in one process.

Two ROS nodes, ``sim_bridge`` and ``nf_controller``, with their own names, parameters, topics,
services and actions, as when they run apart; but the 1 kHz state -> torque call is a direct call
from the simulator's driver thread into the controller's core (``ControllerHost``), never a DDS
round trip. One executor thread serves both nodes' slow side (policy, RunEpisode, rollouts,
status, diagnostics, reset, clear_fault).

    nf_sim_stack --ros-args --params-file config/gear.yaml -p nf_controller:idle_mode:=pause

``sim_bridge``'s ``mode`` picks lockstep (as fast as the physics allows) or realtime (1 kHz wall
clock, the simulator times itself as a robot's driver would).
"""

from __future__ import annotations

import sys

from rclpy.node import Node

from nf_controller_node.node import NFControllerNode
from nf_core.ros_runtime import freeze_heap, run_node
from sim_bridge_node.node import SimBridgeNode

# GIL hand-over interval (s) of the composed process in realtime mode. Python's default, 5 ms, lets
# a busy executor thread keep a waking driver thread waiting for up to 5 ms; 100 us bounds that wait
# to a tenth of a control period (bench/bench_realtime.py --composed measures what it costs and
# gives). Lockstep keeps the default: nothing waits on a wall clock there, and every forced
# hand-over between the driver and the executor thread costs steps.
SWITCH_INTERVAL = 1e-4


def make_nodes() -> list[Node]:
    """The controller (composed) and the simulated arm that ticks it."""
    controller = NFControllerNode(composed=True)
    sim = SimBridgeNode(host=controller.host)
    controller.attach_driver(sim.driver)
    return [controller, sim]


def _start(nodes: list[Node]) -> None:
    freeze_heap()  # no full garbage collection of the start-up objects inside the 1 kHz loop
    for node in nodes:
        if isinstance(node, SimBridgeNode):
            if not node.lockstep:
                sys.setswitchinterval(SWITCH_INTERVAL)
            node.start_driver()


def main(args: list[str] | None = None) -> int:
    """Console script ``nf_sim_stack``."""
    return run_node(make_nodes, "nf_sim_stack", "The MuJoCo Panda and the stable flow controller composed in "
                    "one process (the 1 kHz tick is a direct call; both nodes keep their ROS interfaces).",
                    args, started=_start)


if __name__ == "__main__":
    raise SystemExit(main())
