"""The franky-sim rig: franky-sim (a MuJoCo FR3 behind the libfranka protocol, on 127.0.0.1 only) as
the robot of the tests and benchmarks, started and stopped by its PID, optionally changed before its
scene is compiled.

    python -m nf_bringup.testing.franky                  # as `franky-sim -s mujoco --hostname 127.0.0.1`
    python -m nf_bringup.testing.franky --frictionless
    python -m nf_bringup.testing.franky --gear [--gear-load] [--frictionless] [--task FILE]
    kill -USR1 <its PID>                                 # a reflex: the running motion is aborted
    kill -USR2 <its PID>                                 # --gear: a hand pushes the arm onto the fixture

    with FrankySim(Path("franky-sim.log"), gear=True) as sim:   # then connect pylibfranka to 127.0.0.1
        ...

The launcher builds franky-sim's simulator with its own public classes, in its console script's order.
``--frictionless`` zeroes the arm joints' ``frictionloss``: that Coulomb friction stops a Cartesian
spring short by friction / stiffness, which would hide the controller's own free-space error.
``--gear`` adds our gear scene's shaft (its mouth at the driver's default ``fixture_position``) and
welds the gear to the hand, built by the same builders as our MuJoCo scenes so the numbers agree;
franky-sim's own geoms touch neither. ``--task`` builds that cell from a gear task file instead: its part,
shaft and friction, the shaft's mouth at the file's fixture position. ``--gear-load`` also gives the gear
to franky-sim's gravity compensation as the end-effector load, as Desk's settings do on a real arm.

franky-sim simulates no collisions and so no reflexes. ``SIGUSR1`` makes one: the running motion's
Move command is answered ``kReflexAborted`` and the robot goes idle, holding where it is, as a real
arm does after a reflex; libfranka then raises its "motion aborted by reflex" ``ControlException`` in
the driver, and franky-sim accepts the automatic error recovery that follows.

``SIGUSR2`` (with ``--gear``) puts a person's hand on the arm for hand-guiding tests: a spring on the
TCP (``Hand``) pulls it from where it is along the path a person would show (``nf_core.task_spec.scripted_waypoints``:
over the task's clamp, if it has one, then down onto the shaft), holds the hand's orientation, and lets
go once the path is done. It is a force on the hand body (MuJoCo's ``xfrc_applied``), so the arm moves
only when the driver lets it (zero torque, ``franka_driver``'s ``guide``); under a stiff controller the
hand barely moves it.
"""

from __future__ import annotations

import argparse
import logging
import signal
import socket
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from nf_bringup.processes import ros_env, stop_process

HOST = "127.0.0.1"
PORT = 1337  # libfranka's command port
READY = "Connect to the server"  # franky-sim's line once it serves


def port_busy(host: str = HOST, port: int = PORT) -> bool:
    """True when something already listens on the robot port (another simulator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex((host, port)) == 0


class FrankySim:
    """franky-sim as a child process (context manager), its output in ``log_path``; ``frictionless``,
    ``gear`` and ``gear_load`` start this module's launcher with those options instead of
    ``franky-sim -s mujoco``, as does ``reflexes`` (for ``inject_reflex``) without them."""

    def __init__(self, log_path: Path, timeout: float = 60.0, frictionless: bool = False,
                 gear: bool = False, gear_load: bool = False, reflexes: bool = False, task: str | None = None) -> None:
        if port_busy():
            raise RuntimeError(f"{HOST}:{PORT} is taken: another robot simulator runs on this machine")
        if gear_load and not gear:
            raise ValueError("gear_load needs gear")
        self.log_path = log_path
        self.frictionless = frictionless
        self.gear = gear
        flags = [f for f, on in (("--frictionless", frictionless), ("--gear", gear), ("--gear-load", gear_load)) if on]
        if task is not None:
            if not gear:
                raise ValueError("task needs gear")
            flags += ["--task", str(task)]
        if flags or reflexes:
            cmd = [sys.executable, "-m", "nf_bringup.testing.franky", *flags]
        else:
            cmd = [str(Path(sys.executable).parent / "franky-sim"), "-s", "mujoco", "--hostname", HOST]
        self._log = open(log_path, "w")  # closed in stop
        # ros_env for the package sources on PYTHONPATH; franky-sim itself speaks no DDS
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT, env=ros_env(None))
        deadline = time.monotonic() + timeout
        while READY not in log_path.read_text():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"{' '.join(cmd)} did not start:\n{log_path.read_text()}")
            time.sleep(0.1)

    @property
    def pid(self) -> int:
        """The simulator's PID."""
        return self.proc.pid

    def inject_reflex(self, timeout: float = 5.0) -> str:
        """A reflex now (SIGUSR1 to this launcher): the line the simulator logged about it. Only the
        launcher answers the signal (``reflexes``, or any of its options)."""
        if self.proc.args[0] != sys.executable:
            raise RuntimeError("inject_reflex needs FrankySim(..., reflexes=True)")
        return self._signal(signal.SIGUSR1, "SIGUSR1", timeout)

    def push_hand(self, timeout: float = 5.0) -> str:
        """Put the scripted hand on the arm now (SIGUSR2; ``gear`` only): the line the simulator logged."""
        if not self.gear:
            raise RuntimeError("push_hand needs FrankySim(..., gear=True)")
        return self._signal(signal.SIGUSR2, "SIGUSR2", timeout)

    def _signal(self, sig: int, tag: str, timeout: float) -> str:
        before = self.log_path.read_text().count(tag)
        self.proc.send_signal(sig)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            lines = [ln for ln in self.log_path.read_text().splitlines() if tag in ln]
            if len(lines) > before:
                return lines[-1]
            time.sleep(0.02)
        raise RuntimeError(f"franky-sim did not answer {tag} within {timeout} s")

    def stop(self) -> None:
        """SIGINT (its clean shutdown), then SIGKILL, by PID."""
        stop_process(self.proc, 5.0)
        self._log.close()

    def __enter__(self) -> FrankySim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


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


def gear_task_elements(mouth_in_world: np.ndarray, task: str = "gear") -> tuple[ET.Element, list[ET.Element]]:
    """(gear body for the hand, [shaft body, clamp body if the task has one] for the world) as MJCF
    elements, built by our gear scene's own builders from ``task`` (a gear task file) and moved so the
    pin's top face is at ``mouth_in_world``."""
    import mujoco

    from nf_core.task_spec import load_task
    from sim_bridge_node import scenes
    from sim_bridge_node.held_parts import add_gear

    cell = load_task(task)
    if cell.kind != "gear":
        raise ValueError(f"franky-sim's cell holds a gear task; {task!r} is a {cell.kind} task")
    spec = mujoco.MjSpec()
    hand = spec.worldbody.add_body()
    hand.name = "hand"
    part = add_gear(hand, cell.part)
    for geom in spec.body(part.body).geoms:  # as the gear scene does for the held part
        if geom.contype:
            scenes.contact_params(geom)
            geom.friction[0] = cell.friction
    scenes.add_shaft(spec, cell.fixture)  # base block, shoulder, pin; top face at the file's position
    if cell.clamp is not None:
        scenes.add_clamp(spec, cell.clamp, cell.fixture.position[1])
    root = ET.fromstring(spec.to_xml())
    gear = root.find(f".//body[@name='{part.body}']")
    fixed = [root.find(f".//body[@name='{name}']") for name in (SHAFT_BODY, *(("clamp",) if cell.clamp else ()))]
    if gear is None or any(body is None for body in fixed):
        raise RuntimeError("the gear scene's builders made no gear, shaft or clamp body")
    gear.set("childclass", "main")  # not franky-sim's "fr3" class defaults (site group etc.)
    shift = np.asarray(mouth_in_world, float) - cell.top
    for body in fixed:
        pos = np.fromstring(body.get("pos", "0 0 0"), sep=" ") + shift
        body.set("pos", " ".join(f"{v:.6g}" for v in pos))
    return gear, fixed


def add_gear_task(sim: Any, mouth_in_base: np.ndarray, task: str = "gear") -> None:
    """Weld ``task``'s gear to franky-sim's FR3 hand and put its shaft with the mouth at ``mouth_in_base``
    (robot0's base frame) into the scene, before it is compiled."""
    bodies = {b.get("name"): b for b in sim.worldbody.iter("body")}
    if HAND_BODY not in bodies or BASE_BODY not in bodies:
        raise RuntimeError(f"franky-sim's scene has no {HAND_BODY!r} or {BASE_BODY!r} body")
    base = bodies[BASE_BODY]
    if base.get("quat") or base.get("euler") or base.get("axisangle"):
        raise RuntimeError(f"{BASE_BODY} is turned in the world; the fixture placement assumes it is not")
    base_pos = np.fromstring(base.get("pos", "0 0 0"), sep=" ")
    gear, fixed = gear_task_elements(base_pos + np.asarray(mouth_in_base, float), task)
    bodies[HAND_BODY].append(gear)
    for body in fixed:
        sim.worldbody.append(body)
    option = sim.scene.find("option")
    if option is None:
        option = ET.SubElement(sim.scene, "option")
    ET.SubElement(option, "flag", multiccd="disable")  # as scenes.py does for its own scenes


def configure_gear_load(robot: Any, task: str = "gear") -> tuple[float, np.ndarray]:
    """Tell franky-sim's dynamics model (its gravity compensation) about ``task``'s gear as the robot's
    end-effector load: mass, centre of mass in the flange frame, inertia (column-major). Returns
    (mass, centre of mass in the flange frame)."""
    from nf_core.task_spec import load_task

    part = load_task(task).part.inertia()

    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    flange_R_hand = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # hand = flange turned -45 deg
    com = flange_R_hand @ part.com_in_hand
    inertia = flange_R_hand @ part.inertia @ flange_R_hand.T
    robot.set_load(float(part.mass), tuple(com), tuple(inertia.flatten(order="F")))
    return float(part.mass), com


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


def add_robot(sim: Any, frictionless: bool, gear: bool = False, task: str | None = None) -> Any:
    """Add franky-sim's one FR3 to an initialized ``MujocoSimulator`` (as its CLI does) and, when
    ``frictionless``, zero the arm joints' ``frictionloss`` in the scene before it is compiled;
    when ``gear``, add the gear task (``add_gear_task``): the gear task's at the driver's default fixture
    position, or ``task``'s (a gear task file) at its own fixture position."""
    robot = sim.add_robot()
    if frictionless:
        remove_arm_friction(sim.scene)
    if gear and task is None:
        add_gear_task(sim, default_fixture_mouth())
    elif gear:
        from nf_core.task_spec import load_task

        add_gear_task(sim, load_task(task).top, task)
    return robot


def joint_frictionloss(model: Any, names: list[str]) -> list[float]:
    """The compiled model's ``dof_frictionloss`` (Nm) of the named joints."""
    import mujoco

    return [float(model.dof_frictionloss[model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)]])
            for n in names]


def inject_reflex(server: Any) -> list[int]:
    """Abort every robot's running motion as a reflex does (its Move answered ``kReflexAborted``, the
    robot idle and holding); the ids of the motions aborted (none: no motion ran)."""
    from franky_sim.franka_robot_protocol import MoveStatus, RobotCommand
    from franky_sim.franka_server import BaseCommand

    aborted = []
    for rs in server.robot_servers:
        motion = rs.current_motion_id
        if motion:
            rs.stop_motion(send_preemption_signal=False)
            rs.reset_current_motion_id()
            BaseCommand.send_response(rs._tcp_socket, RobotCommand.kMove, motion, MoveStatus.kReflexAborted)
            aborted.append(motion)
    return aborted


class Hand:
    """A person's hand on the arm (``SIGUSR2``): a spring of ``stiffness`` N/m with ``damping`` N s/m on the
    TCP, its force bounded to ``max_force`` N, pulls towards a point that walks ``scripted_waypoints``
    at ``speed`` m/s from the TCP where the push began; a rotational spring (``k_rot`` Nm/rad, ``d_rot``
    Nm s/rad) keeps the hand in the insertion orientation (the part square to the fixture, as a person
    holds it; ``panda_spec.INSERTION_ROTATION``, the controller's). On the path's last leg a slow integral term
    (``integral`` N/(m s), bounded to ``max_integral`` N) leans into what holds the part back, as a person
    does. It lets go ``hold`` s after the point reached the path's end. No two pushes are alike, as no two of
    a person's are: push k draws (from seed k) the path's middle waypoints up to ``vary`` m off in y and z
    (the last leg down the fixture's axis only in height) and its speed within 20 %. Positions in the world
    frame of the compiled model (the robot's base is not turned in it: ``add_gear_task`` checks)."""

    def __init__(self, model: Any, data: Any, task: str, stiffness: float = 800.0,
                 damping: float = 60.0, max_force: float = 40.0, speed: float = 0.12, k_rot: float = 30.0,
                 d_rot: float = 3.0, integral: float = 400.0, max_integral: float = 10.0, hold: float = 2.0,
                 vary: float = 0.02) -> None:
        import mujoco

        from nf_core.panda_spec import GEAR_PART, INSERTION_ROTATION
        from nf_core.task_spec import load_task

        self.model, self.data, self.task = model, data, load_task(task)
        self.base = data.xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, BASE_BODY)].copy()
        self.body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, HAND_BODY)
        self.site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, GEAR_PART.tcp_site)
        self.stiffness, self.damping, self.max_force, self.speed = stiffness, damping, max_force, speed
        self.k_rot, self.d_rot, self.integral, self.max_integral, self.hold = k_rot, d_rot, integral, max_integral, hold
        self.path: list[np.ndarray] = []  # waypoints left, world frame
        self.point = np.zeros(3)  # where the spring pulls now
        self.R0 = INSERTION_ROTATION  # the hand's orientation to keep (the robot's base is not turned)
        self.i_force = np.zeros(3)
        self.release_in = 0.0  # s left after the path's end
        self.active = False
        self.vary = vary
        self.pushes = 0
        self.pace = speed  # m/s of this push

    def tcp(self) -> np.ndarray:
        """The TCP (the held part's leading face), world frame."""
        return self.data.site_xpos[self.site].copy()

    def tilt(self) -> float:
        """Degrees between the hand's orientation and the insertion orientation."""
        R = self.data.xmat[self.body].reshape(3, 3)
        return float(np.degrees(np.arccos(np.clip((np.trace(self.R0.T @ R) - 1.0) / 2.0, -1.0, 1.0))))

    def begin(self) -> str:
        """Grab the arm where it is and start along the path; a line for the log."""
        from nf_core.task_spec import scripted_waypoints

        x = self.tcp()
        rng = np.random.default_rng(self.pushes)
        self.pushes += 1
        path = scripted_waypoints(self.task, x - self.base)
        for w in path[1:-2]:  # the way between, not where it starts or its last leg
            w[1:] += rng.uniform(-self.vary, self.vary, 2)
        if len(path) > 2:  # the last leg stays on the fixture's axis: only its height varies
            path[-2][2] += rng.uniform(-self.vary, self.vary)
        self.pace = self.speed * rng.uniform(0.8, 1.2)
        self.path = [self.base + w for w in path]
        self.point = x
        tilt = self.tilt()
        self.i_force[:] = 0.0
        self.release_in, self.active = self.hold, True
        return (f"hand on the arm (SIGUSR2): from TCP {np.round(x - self.base, 4).tolist()} m through "
                f"{len(self.path)} waypoints (base frame), the hand {tilt:.1f} deg from the insertion orientation")

    def step(self, dt: float) -> str:
        """Set the hand's wrench for the next physics step of ``dt`` s; a line for the log when it lets go."""
        import mujoco

        wrench = self.data.xfrc_applied[self.body]
        if not self.active:
            return ""
        if self.path:  # the point walks towards the next waypoint
            delta = self.path[0] - self.point
            dist = float(np.linalg.norm(delta))
            if dist <= self.pace * dt:
                self.point = self.path.pop(0)
            else:
                self.point = self.point + delta * (self.pace * dt / dist)
        else:
            self.release_in -= dt
            if self.release_in <= 0.0:
                wrench[:] = 0.0
                self.active = False
                return (f"hand off the arm: TCP {np.round(self.tcp() - self.base, 4).tolist()} m (base frame), "
                        f"the hand {self.tilt():.1f} deg from the insertion orientation")
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_SITE, self.site, vel, 0)
        error = self.point - self.tcp()
        if len(self.path) <= 1:  # on the last leg: lean in
            self.i_force = np.clip(self.i_force + self.integral * error * dt, -self.max_integral, self.max_integral)
        force = self.stiffness * error - self.damping * vel[3:] + self.i_force
        norm = float(np.linalg.norm(force))
        if norm > self.max_force:
            force *= self.max_force / norm
        R = self.data.xmat[self.body].reshape(3, 3)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, (self.R0 @ R.T).flatten())
        rot = np.zeros(3)
        mujoco.mju_quat2Vel(rot, quat, 1.0)  # rotation from R to R0, world frame
        torque = self.k_rot * rot - self.d_rot * vel[:3]
        # the force acts at the TCP; xfrc_applied acts at the body's centre of mass
        torque = torque + np.cross(self.tcp() - self.data.xipos[self.body], force)
        wrench[:3], wrench[3:] = force, torque
        return ""


def serve(server: Any, hand: Hand | None = None) -> None:
    """franky-sim's 1 kHz loop (``run_forever``), with a reflex injected on each ``SIGUSR1`` and, with a
    ``hand``, the hand put on the arm on each ``SIGUSR2``."""
    wanted: list[bool] = []
    pushes: list[bool] = []
    signal.signal(signal.SIGUSR1, lambda *_: wanted.append(True))
    signal.signal(signal.SIGUSR2, lambda *_: pushes.append(True))
    server.running = True
    dt = float(hand.model.opt.timestep) if hand is not None else 0.0
    while server.running:
        if wanted:
            wanted.clear()
            aborted = inject_reflex(server)
            print(f"reflex injected (SIGUSR1): motion {aborted} aborted" if aborted
                  else "reflex asked for (SIGUSR1), but no motion runs: nothing aborted", flush=True)
        if pushes:
            pushes.clear()
            print(hand.begin() if hand is not None else "SIGUSR2 needs --gear (no hand without a cell)", flush=True)
        if hand is not None:
            line = hand.step(dt)
            if line:
                print(line, flush=True)
        server.run_once(True)


def main(argv: list[str] | None = None) -> None:
    """``python -m nf_bringup.testing.franky``: serve franky-sim's FR3 until interrupted."""
    parser = argparse.ArgumentParser(prog="python -m nf_bringup.testing.franky",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--frictionless", action="store_true",
                        help="zero the arm joints' frictionloss (the only change to franky-sim's FR3)")
    parser.add_argument("--gear", action="store_true",
                        help="add the gear task's shaft (mouth at the driver's default fixture_position) "
                             "and weld the gear to the hand")
    parser.add_argument("--gear-load", action="store_true",
                        help="with --gear: configure the gear as the robot's end-effector load, so "
                             "franky-sim's gravity compensation includes it")
    parser.add_argument("--task", default=None, metavar="FILE",
                        help="with --gear: the cell of this gear task file (part, shaft, friction, the mouth at its "
                             "fixture position) instead of the gear task's at the driver's default")
    args = parser.parse_args(argv)
    if args.gear_load and not args.gear:
        parser.error("--gear-load needs --gear")
    if args.task is not None and not args.gear:
        parser.error("--task needs --gear")

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
        robot = add_robot(sim, args.frictionless, args.gear, args.task)
        if args.gear_load:
            mass, com = configure_gear_load(robot, args.task or "gear")
            print(f"end-effector load: {mass:.3f} kg at {com.round(4).tolist()} m in the flange frame", flush=True)
        with franky_sim.SimulationServer(sim, hostname_candidates=[HOST]) as server:
            names = [j.get("name", "") for j in arm_joints(sim.scene)]
            values = joint_frictionloss(sim.model, names)
            report = ", ".join(f"{n} {v:.3f}" for n, v in zip(names, values, strict=True))
            print(f"arm joint frictionloss (Nm): {report}", flush=True)
            if args.gear:
                print(gear_report(sim.model, sim.data), flush=True)
            print(f"{READY} using '{robot.hostname}' as the robot IP address", flush=True)
            hand = Hand(sim.model, sim.data, args.task or "gear") if args.gear else None
            try:
                serve(server, hand)
            except KeyboardInterrupt:
                print("\nShutting down server...", flush=True)


if __name__ == "__main__":
    main()
