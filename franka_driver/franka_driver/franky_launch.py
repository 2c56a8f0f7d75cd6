"""franky-sim's MuJoCo FR3 server started from Python, optionally without joint friction and/or
with the gear task's fixture and gear.

    python -m franka_driver.franky_launch               # as `franky-sim -s mujoco --hostname 127.0.0.1`
    python -m franka_driver.franky_launch --frictionless
    python -m franka_driver.franky_launch --gear [--gear-load] [--frictionless]

Builds the simulator with franky-sim's own public classes in the order its console script does
(``MujocoSimulator()``, ``add_robot()``, ``SimulationServer`` bound to 127.0.0.1 only,
``run_forever()``). With ``--frictionless`` the scene's seven arm joints get ``frictionloss="0"``
before the MuJoCo model is compiled: the only change. franky-sim's FR3 has Coulomb friction
(``frictionloss`` 0.25-1.14 Nm per joint), which stops a Cartesian spring short by about
friction / stiffness; without it a free-space error measures the controller's model and the
simulator's gravity compensation alone. The finger joints keep theirs (the hand is held by
franky-sim's own finger controller). The compiled values are printed before the "Connect to the
server" line that ``FrankySim`` waits for. SIGINT stops it cleanly, as it does franky-sim.

``--gear`` adds, before the compile, the gear task of our own simulator (``sim_bridge_node.scenes``
and ``held_parts``, the same builders, so the same numbers): the stepped shaft on its base block
as fixed world geoms, moved so its mouth (the pin's top face) is at the driver's default
``fixture_position`` in robot0's base frame, and the gear ring welded to ``robot0_hand`` (the
description's ``fr3_hand``: the flange turned -45 deg about z) with the held-part spec's pose,
mass and inertia, so the driver's TCP model (``held_part: gear``) is where the simulated gear is.
Contacts: the gear's and the fixture's contact bits, solref, solimp and friction of our scenes,
multi-point convex collision off as there. franky-sim's own geoms (arm, hand, fingers, floor)
keep contype = conaffinity = 1, so they touch neither the gear nor the shaft. At franky-sim's
initial hand width (40 mm) the fingertip pads sit 21.5-29.5 mm from the axis and reach 8 mm below
the gear's top face, into the ring's volume (as if gripping it), clear of the 14 mm pin and 12 mm
above the shoulder at full depth; closed fingers would enter the bore, where our gear scene
excludes the finger-shaft pairs and the contact bits do it here. franky-sim's gravity
compensation does not know the gear (0.12 kg) unless ``--gear-load`` configures it as the
robot's end-effector load (what Desk's end-effector settings do on a real arm; libfranka's
``setLoad`` does the same at run time).
"""

from __future__ import annotations

import argparse
import logging
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

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


ROBOT_PREFIX = "robot0_"  # franky-sim's prefix of its first (only) robot
HAND_BODY = ROBOT_PREFIX + "hand"  # MuJoCo body of the FR3 hand = the description's fr3_hand frame
BASE_BODY = ROBOT_PREFIX + "base"
GEAR_BODY = "gear"  # names of our scenes (unique in franky-sim's scene)
SHAFT_BODY = "shaft"
PIN_GEOM = "shaft_pin"


def default_fixture_mouth() -> np.ndarray:
    """The driver's default ``fixture_position`` (m, robot base frame): where ``--gear`` puts the
    shaft's top face."""
    from franka_driver.loop import DriverConfig

    return DriverConfig().fixture_position.copy()


def gear_task_elements(mouth_in_world: np.ndarray) -> tuple[ET.Element, ET.Element]:
    """(gear body for the hand, shaft body for the world) as MJCF elements, built by our gear
    scene's own builders and moved so the pin's top face is at ``mouth_in_world``."""
    import mujoco

    from sim_bridge_node import scenes
    from sim_bridge_node.held_parts import add_gear

    spec = mujoco.MjSpec()
    hand = spec.worldbody.add_body()
    hand.name = "hand"
    part = add_gear(hand)
    for geom in spec.body(part.body).geoms:  # as the gear scene does for the held part
        if geom.contype:
            scenes.contact_params(geom)
    scenes.add_shaft(spec)  # base block, shoulder, pin; top face at FIXTURE_TOP over FIXTURE_XY
    root = ET.fromstring(spec.to_xml())
    gear = root.find(f".//body[@name='{part.body}']")
    shaft = root.find(f".//body[@name='{SHAFT_BODY}']")
    if gear is None or shaft is None:
        raise RuntimeError("the gear scene's builders made no gear or shaft body")
    gear.set("childclass", "main")  # not franky-sim's "fr3" class defaults (site group etc.)
    shift = np.asarray(mouth_in_world, float) - np.array([*scenes.FIXTURE_XY, scenes.FIXTURE_TOP])
    pos = np.fromstring(shaft.get("pos", "0 0 0"), sep=" ") + shift
    shaft.set("pos", " ".join(f"{v:.6g}" for v in pos))
    return gear, shaft


def add_gear_task(sim: Any, mouth_in_base: np.ndarray) -> None:
    """Weld the gear to franky-sim's FR3 hand and put the shaft with its mouth at ``mouth_in_base``
    (robot0's base frame) into the scene, before it is compiled."""
    bodies = {b.get("name"): b for b in sim.worldbody.iter("body")}
    if HAND_BODY not in bodies or BASE_BODY not in bodies:
        raise RuntimeError(f"franky-sim's scene has no {HAND_BODY!r} or {BASE_BODY!r} body")
    base = bodies[BASE_BODY]
    if base.get("quat") or base.get("euler") or base.get("axisangle"):
        raise RuntimeError(f"{BASE_BODY} is turned in the world; the fixture placement assumes it is not")
    base_pos = np.fromstring(base.get("pos", "0 0 0"), sep=" ")
    gear, shaft = gear_task_elements(base_pos + np.asarray(mouth_in_base, float))
    bodies[HAND_BODY].append(gear)
    sim.worldbody.append(shaft)
    option = sim.scene.find("option")
    if option is None:
        option = ET.SubElement(sim.scene, "option")
    ET.SubElement(option, "flag", multiccd="disable")  # as scenes.py does for its own scenes


def configure_gear_load(robot: Any) -> tuple[float, np.ndarray]:
    """Tell franky-sim's dynamics model (its gravity compensation) about the gear as the robot's
    end-effector load: mass, centre of mass in the flange frame, inertia (column-major). Returns
    (mass, centre of mass in the flange frame)."""
    from nf_core.panda_spec import GEAR_PART

    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    flange_R_hand = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # hand = flange turned -45 deg
    com = flange_R_hand @ GEAR_PART.com_in_hand
    inertia = flange_R_hand @ GEAR_PART.inertia @ flange_R_hand.T
    robot.set_load(float(GEAR_PART.mass), tuple(com), tuple(inertia.flatten(order="F")))
    return float(GEAR_PART.mass), com


def gear_report(model: Any, data: Any) -> str:
    """The compiled gear task: fixture mouth (base frame and world), the gear's body, mass, TCP."""
    import mujoco

    from nf_core.panda_spec import GEAR_PART

    def body(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)

    pin = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, PIN_GEOM)
    mouth = data.geom_xpos[pin] + data.geom_xmat[pin].reshape(3, 3)[:, 2] * model.geom_size[pin, 1]
    base = data.xpos[body(BASE_BODY)]
    hand, gear = body(HAND_BODY), body(GEAR_BODY)
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, GEAR_PART.tcp_site)
    R = data.xmat[hand].reshape(3, 3)
    tcp_in_hand = R.T @ (data.site_xpos[site] - data.xpos[hand])
    com_in_hand = R.T @ (data.xipos[gear] - data.xpos[hand])
    parent = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.body_parentid[gear]))

    def fmt(v: np.ndarray) -> str:
        return "[" + ", ".join(f"{x:.4f}" for x in v) + "]"

    return (f"gear fixture: mouth {fmt(mouth - base)} m in {BASE_BODY}'s frame ({fmt(mouth)} world); "
            f"gear attached to {parent}: mass {model.body_mass[gear]:.3f} kg, COM {fmt(com_in_hand)} m and "
            f"TCP {fmt(tcp_in_hand)} m in the hand frame")


def add_robot(sim: Any, frictionless: bool, gear: bool = False) -> Any:
    """Add franky-sim's one FR3 to an initialized ``MujocoSimulator`` (as its CLI does) and, when
    ``frictionless``, zero the arm joints' ``frictionloss`` in the scene before it is compiled;
    when ``gear``, add the gear task (``add_gear_task``) at the driver's default fixture position."""
    robot = sim.add_robot()
    if frictionless:
        remove_arm_friction(sim.scene)
    if gear:
        add_gear_task(sim, default_fixture_mouth())
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
    parser.add_argument("--gear", action="store_true",
                        help="add the gear task's shaft (mouth at the driver's default fixture_position) "
                             "and weld the gear to the hand")
    parser.add_argument("--gear-load", action="store_true",
                        help="with --gear: configure the gear as the robot's end-effector load, so "
                             "franky-sim's gravity compensation includes it")
    args = parser.parse_args(argv)
    if args.gear_load and not args.gear:
        parser.error("--gear-load needs --gear")

    import franky_sim
    from franky_sim.mujoco_simulator import MujocoSimulator

    # as franky-sim's console script: warnings only, numba quiet
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s - %(levelname)s - %(message)s")
    logging.getLogger("numba").setLevel(logging.WARNING)

    changes = [c for c, on in (("arm joints without friction", args.frictionless), ("gear task", args.gear),
                               ("gear as end-effector load", args.gear_load)) if on]
    print(f"Starting Mujoco simulation server without visualization"
          f"{' (' + ', '.join(changes) + ')' if changes else ''}", flush=True)
    with MujocoSimulator(enable_visualization=False) as sim:
        robot = add_robot(sim, args.frictionless, args.gear)
        if args.gear_load:
            mass, com = configure_gear_load(robot)
            print(f"end-effector load: {mass:.3f} kg at {com.round(4).tolist()} m in the flange frame", flush=True)
        with franky_sim.SimulationServer(sim, hostname_candidates=[HOST]) as server:
            names = [j.get("name", "") for j in arm_joints(sim.scene)]
            values = joint_frictionloss(sim.model, names)
            report = ", ".join(f"{n} {v:.3f}" for n, v in zip(names, values, strict=True))
            print(f"arm joint frictionloss (Nm): {report}", flush=True)
            if args.gear:
                print(gear_report(sim.model, sim.data), flush=True)
            print(f"Connect to the server using '{robot.hostname}' as the robot IP address", flush=True)
            try:
                server.run_forever()
            except KeyboardInterrupt:
                print("\nShutting down server...", flush=True)


if __name__ == "__main__":
    main()
