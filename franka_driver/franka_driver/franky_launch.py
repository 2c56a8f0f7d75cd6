"""franky-sim's MuJoCo FR3 server started from Python, optionally without joint friction.

    python -m franka_driver.franky_launch               # as `franky-sim -s mujoco --hostname 127.0.0.1`
    python -m franka_driver.franky_launch --frictionless

Builds the simulator with franky-sim's own public classes in the order its console script does
(``MujocoSimulator()``, ``add_robot()``, ``SimulationServer`` bound to 127.0.0.1 only,
``run_forever()``). With ``--frictionless`` the scene's seven arm joints get ``frictionloss="0"``
before the MuJoCo model is compiled: the only change. franky-sim's FR3 has Coulomb friction
(``frictionloss`` 0.25-1.14 Nm per joint), which stops a Cartesian spring short by about
friction / stiffness; without it a free-space error measures the controller's model and the
simulator's gravity compensation alone. The finger joints keep theirs (the hand is held by
franky-sim's own finger controller). The compiled values are printed before the "Connect to the
server" line that ``FrankySim`` waits for. SIGINT stops it cleanly, as it does franky-sim.
"""

from __future__ import annotations

import argparse
import logging
import xml.etree.ElementTree as ET
from typing import Any

from franka_driver.simulator import HOST

ARM_JOINTS = tuple(f"fr3_joint{i}" for i in range(1, 8))  # franky-sim prefixes them with "robot<i>_"


def arm_joints(scene: ET.Element) -> list[ET.Element]:
    """The ``<joint>`` elements of the arm (seven per robot) in an MJCF scene, in order."""
    found = [j for j in scene.iter("joint") if j.get("name", "").endswith(ARM_JOINTS)]
    if not found or len(found) % len(ARM_JOINTS):
        raise RuntimeError(f"expected 7 arm joints per robot in franky-sim's scene, found "
                           f"{[j.get('name') for j in found]}")
    return found


def remove_arm_friction(scene: ET.Element) -> list[str]:
    """Set ``frictionloss="0"`` on every arm joint of the scene (overrides the class default of
    joints 1-4 and the values of 5-7); returns the joint names changed."""
    joints = arm_joints(scene)
    for joint in joints:
        joint.set("frictionloss", "0")
    return [j.get("name", "") for j in joints]


def add_robot(sim: Any, frictionless: bool) -> Any:
    """Add franky-sim's one FR3 to an initialized ``MujocoSimulator`` (as its CLI does) and, when
    ``frictionless``, zero the arm joints' ``frictionloss`` in the scene before it is compiled."""
    robot = sim.add_robot()
    if frictionless:
        remove_arm_friction(sim.scene)
    return robot


def joint_frictionloss(model: Any, names: list[str]) -> list[float]:
    """The compiled model's ``dof_frictionloss`` (Nm) of the named joints."""
    import mujoco

    return [float(model.dof_frictionloss[model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)]])
            for n in names]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frictionless", action="store_true",
                        help="zero the arm joints' frictionloss (the only change to franky-sim's FR3)")
    args = parser.parse_args(argv)

    import franky_sim
    from franky_sim.mujoco_simulator import MujocoSimulator

    # as franky-sim's console script: warnings only, numba quiet
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s - %(levelname)s - %(message)s")
    logging.getLogger("numba").setLevel(logging.WARNING)

    print(f"Starting Mujoco simulation server without visualization"
          f"{' (arm joints without friction)' if args.frictionless else ''}", flush=True)
    with MujocoSimulator(enable_visualization=False) as sim:
        robot = add_robot(sim, args.frictionless)
        with franky_sim.SimulationServer(sim, hostname_candidates=[HOST]) as server:
            names = [j.get("name", "") for j in arm_joints(sim.scene)]
            values = joint_frictionloss(sim.model, names)
            report = ", ".join(f"{n} {v:.3f}" for n, v in zip(names, values, strict=True))
            print(f"arm joint frictionloss (Nm): {report}", flush=True)
            print(f"Connect to the server using '{robot.hostname}' as the robot IP address", flush=True)
            try:
                server.run_forever()
            except KeyboardInterrupt:
                print("\nShutting down server...", flush=True)


if __name__ == "__main__":
    main()
