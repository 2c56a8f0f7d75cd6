"""``teach`` (``make teach``): record demonstrations as bags, by teleoperation through the stable law.

The simulated arm and its controller (``nf_sim_stack``) run a teaching policy: the identity flow with
soft gains, whose anchor x_ref the operator pulls (the controller's ``teleop_speed``: the anchor moves
towards the points on ``teleop/target`` at most that fast, from the TCP at each episode's start). The
operator thus pulls a virtual spring on the TCP and the arm stays under
u = -J^T S [phi(x) - phi(x_ref)] - J^T D J xdot with the pull bounded (``--force-bound``): no
command of the operator reaches the joints but through that law.

Each demonstration is one episode (``run_episode``, a start drawn from the task file's starts) and the
recorder writes them all into one ordinary MCAP bag of the run's topics (joint states, controller
status with the anchor, targets, task status); ``fit_demos`` reads it back.

    teach --task gear_clamp --demos 8                       # a scripted operator (stands in for a person)
    teach --task gear_clamp --demos 3 --operator keyboard   # you, in real time: keys below
    teach --robot franky --task gear_clamp --demos 8        # hand-guiding franky-sim's FR3 (below)
    teach --robot 172.16.0.2 --task my_cell.yaml --demos 5   # you guide a real FR3 / Panda by hand

Hand-guiding (``--robot franky``): the Franka stack (``nf_franka_stack``) with the driver's ``guide`` on,
so each episode, after the reset motion to the task's start, commands zero torque and the arm is moved
by hand, its gravity compensated by the robot; the driver stops a guide into the safe hold on a joint
speed, a joint limit or a time limit (docs/hardware.md). On franky-sim a scripted hand
(``nf_bringup.testing.franky``, SIGUSR2) pushes the TCP over the task's path as a person would. On a real
arm (``--robot <FCI address>``) you do, within ``--seconds`` of each episode's start; the robot PC needs
the realtime kernel, and a reflex waits for you (``/franka_driver/recover``, then ``clear_fault``).

Keys (``--operator keyboard``, real-time simulation): w/s +x/-x, a/d +y/-y, r/f up/down, by ``--step``
(default 1 cm) from where the anchor is; the episode ends after ``--seconds``.

Leaves ``<out>/bag`` (MCAP), ``<out>/demos.json`` (per demonstration: start seed, success, depth, final
distance) and ``<out>/logs``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import yaml

from nf_core.task_spec import TaskSpec, load_task, scripted_waypoints

from .processes import ManagedProcess, allocate_domain_id, ros_env, stop_on_signals
from .stack import SIM_STACK_PARAMS, write_task_parameters

DEMO_SEED_BASE = 500_000_000  # demonstration starts: their own seeds, apart from training's and evaluation's
TEACH_GAINS = (300.0, 40.0)  # N/m, N s/m: the teaching spring S = 300 I, D = 40 I on the identity flow
ARRIVED = 0.002  # m: the scripted operator goes on to the next waypoint once the anchor is this close
KEYS = {"w": (0, 1.0), "s": (0, -1.0), "a": (1, 1.0), "d": (1, -1.0), "r": (2, 1.0), "f": (2, -1.0)}


class ScriptedOperator:
    """Pulls the anchor through ``scripted_waypoints``: the next one once the anchor is within ARRIVED."""

    def __init__(self, task: TaskSpec) -> None:
        self.task = task
        self.path: list[np.ndarray] = []

    def begin(self, tcp: np.ndarray) -> None:
        """A new demonstration from TCP ``tcp``."""
        self.path = scripted_waypoints(self.task, tcp)

    def target(self, anchor: np.ndarray) -> np.ndarray | None:
        """The point to pull to, given where the anchor is (None: nothing to do)."""
        while len(self.path) > 1 and np.linalg.norm(anchor - self.path[0]) < ARRIVED:
            self.path.pop(0)
        return self.path[0] if self.path else None


class KeyboardOperator:
    """Moves the target by ``step`` m per key (``KEYS``) from the anchor; reads the terminal in cbreak mode."""

    def __init__(self, step: float = 0.01) -> None:
        self.step = step
        self.pending: list[str] = []
        self.goal: np.ndarray | None = None
        self._lock = threading.Lock()

    def begin(self, tcp: np.ndarray) -> None:
        """A new demonstration: the target starts at the TCP."""
        self.goal = np.array(tcp, dtype=float)

    def press(self, key: str) -> None:
        """One key (any thread)."""
        with self._lock:
            self.pending.append(key)

    def target(self, anchor: np.ndarray) -> np.ndarray | None:
        """The target after the keys pressed since the last call."""
        with self._lock:
            keys, self.pending = self.pending, []
        for k in keys:
            if k in KEYS and self.goal is not None:
                axis, sign = KEYS[k]
                self.goal[axis] += sign * self.step
        return self.goal

    def read_terminal(self, stop: threading.Event) -> None:
        """Feed key presses from stdin until ``stop`` (a thread's body)."""
        import select
        import termios
        import tty

        fd = sys.stdin.fileno()
        saved = termios.tcgetattr(fd)
        try:
            tty.setcbreak(fd)
            while not stop.is_set():
                if select.select([sys.stdin], [], [], 0.1)[0]:
                    self.press(sys.stdin.read(1))
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)


class PersonOperator:
    """A person guiding a real arm by hand: told when each demonstration begins; nothing to publish."""

    def __init__(self, seconds: float, log: Callable[[str], None] = print) -> None:
        self.seconds = seconds
        self.log = log

    def begin(self, tcp: np.ndarray) -> None:
        """A new demonstration: say so."""
        self.log(f"[teach] zero torque now: guide the arm onto the fixture within {self.seconds:g} s "
                 f"(from TCP {np.round(tcp, 3).tolist()} m)")

    def target(self, anchor: np.ndarray) -> np.ndarray | None:
        """Nothing: the person moves the arm."""
        return None


class HandOperator:
    """franky-sim's scripted hand (``FrankySim.push_hand``), put on the arm as each demonstration begins; it
    pushes by itself, so there is no target to publish."""

    def __init__(self, sim: object, log: Callable[[str], None] = print) -> None:
        self.sim = sim
        self.log = log

    def begin(self, tcp: np.ndarray) -> None:
        """A new demonstration: the hand takes the arm."""
        self.log(f"[teach] {self.sim.push_hand()}")

    def target(self, anchor: np.ndarray) -> np.ndarray | None:
        """Nothing: the hand moves the arm itself."""
        return None


def teaching_policy(task: TaskSpec, n_flow: int, n_hidden: int, activation: str, force_bound: float,
                    version: int = 1) -> object:
    """PolicyParameters of the teaching spring: the identity flow (all weights 0), S = 300 I, D = 40 I,
    x_ref the task's goal (the anchor replaces it from the first tick), the pull bounded to ``force_bound`` N."""
    from nf_core.flow_spec import FlowArchitecture
    from nf_core.policy_params import PolicyLaw, PolicyParameters

    arch = FlowArchitecture(dim=3, n_flow=n_flow, n_hidden=n_hidden, activation=activation)
    s, d = TEACH_GAINS
    return PolicyParameters(arch=arch, weights=np.zeros(arch.n_params), log_std=np.zeros(1),
                            stiffness=s * np.eye(3), damping=d * np.eye(3), x_ref=task.goal_position,
                            version=version, law=PolicyLaw(potential_force_bound=force_bound,
                                                           held_part=task.part.text()))


Operator = ScriptedOperator | KeyboardOperator | HandOperator | PersonOperator


def run_demonstrations(task: TaskSpec, operator: Operator, n: int, seconds: float,
                       first_seed: int, force_bound: float, log: Callable[[str], None] = print) -> list[dict]:
    """Publish the teaching policy, then run ``n`` episodes of ``seconds`` s while ``operator`` pulls the
    anchor; returns each one's result. Needs rclpy initialised and the arm stack running."""
    import rclpy
    from geometry_msgs.msg import PointStamped
    from nf_msgs.action import RunEpisode
    from nf_msgs.msg import ControllerStatus
    from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor

    from nf_core import qos
    from nf_core.topics import CONTROLLER_STATUS, POLICY_PARAMETERS, RUN_EPISODE, TELEOP_TARGET

    node = rclpy.create_node("teach")
    status: dict[str, object] = {"running": 0}

    def on_status(m: ControllerStatus) -> None:
        status["last"] = m
        status["running"] = status["running"] + 1 if m.mode == ControllerStatus.MODE_RUNNING else 0

    node.create_subscription(ControllerStatus, CONTROLLER_STATUS, on_status, qos.STATE)
    target_pub = node.create_publisher(PointStamped, TELEOP_TARGET, qos.STATE)
    policy_pub = node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
    client = ActionClient(node, RunEpisode, RUN_EPISODE)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    results = []
    try:
        policy = teaching_policy(task, 1, 16, "gelu", force_bound)
        policy_pub.publish(policy.fill_msg(PolicyParametersMsg()))
        if not client.wait_for_server(timeout_sec=120.0):
            raise RuntimeError("no run_episode action server after 120 s: is the arm stack up? (see logs/)")
        for k in range(n):
            seed = first_seed + k
            goal = RunEpisode.Goal(policy_version=policy.version, seed=seed, noise_seed=-1, duration=seconds,
                                   deterministic=True)
            sent = client.send_goal_async(goal)
            while not sent.done():
                time.sleep(0.01)
            handle = sent.result()
            if not handle.accepted:
                raise RuntimeError(f"demonstration {k}: the controller refused the episode (see logs/arm.log)")
            result = handle.get_result_async()
            began = False
            while not result.done():
                s = status.get("last")
                # from the third status of the episode on: its anchor (x_ref) started at the TCP of the start
                if s is not None and status["running"] >= 3 and len(s.x_ref) == 3:
                    anchor = np.array(s.x_ref)
                    if not began:
                        operator.begin(anchor)
                        began = True
                    point = operator.target(anchor)
                    if point is not None:
                        msg = PointStamped()
                        msg.header.frame_id = "panda_link0"
                        msg.point.x, msg.point.y, msg.point.z = (float(v) for v in point)
                        target_pub.publish(msg)
                time.sleep(0.02)
            r = result.result().result
            row = {"demo": k, "seed": seed, "completed": bool(r.completed), "success": bool(r.success),
                   "insertion_depth": float(r.insertion_depth), "final_distance": float(r.final_distance),
                   "episode_id": int(r.episode_id), "message": r.message}
            results.append(row)
            log(f"[teach] demonstration {k + 1}/{n} (start seed {seed}): "
                f"{'inserted' if r.success else 'not inserted'}, depth {1e3 * r.insertion_depth:.1f} mm, "
                f"{1e3 * r.final_distance:.1f} mm from the goal" + ("" if r.completed else f"; aborted: {r.message}"))
            status.pop("last", None)
            status["running"] = 0
    finally:
        executor.shutdown()
        node.destroy_node()
    return results


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``teach``."""
    ap = argparse.ArgumentParser(prog="teach", description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="gear_clamp", help="built-in task or task file (default gear_clamp)")
    ap.add_argument("--config", type=Path, default=Path("config/gear_clamp.yaml"),
                    help="the stack's parameters file (config/sim.yaml beside it comes first)")
    ap.add_argument("--demos", type=int, default=8, help="demonstrations to record (default 8)")
    ap.add_argument("--operator", choices=("scripted", "keyboard"), default="scripted",
                    help="simulation: who pulls the anchor (--robot franky: franky-sim's scripted hand)")
    ap.add_argument("--robot", default="sim",
                    help="sim: teleoperation on the simulated arm; franky: hand-guiding franky-sim's FR3 (zero "
                         "torque, a scripted hand); an FCI address: you guide that arm by hand")
    ap.add_argument("--hardware-config", type=Path, default=Path("config/franka.yaml"),
                    help="a Franka (--robot franky or an address): the Franka stack's file")
    ap.add_argument("--seconds", type=float, default=None,
                    help="s per demonstration (default 7; 10 on a Franka)")
    ap.add_argument("--speed", type=float, default=0.15, help="m/s the anchor moves at most (default 0.15)")
    ap.add_argument("--step", type=float, default=0.01, help="m per key (keyboard; default 0.01)")
    ap.add_argument("--force-bound", type=float, default=40.0,
                    help="N: the teaching spring's pull is bounded to this (default 40)")
    ap.add_argument("--first-seed", type=int, default=DEMO_SEED_BASE, help="start seed of the first demonstration")
    ap.add_argument("--out", type=Path, default=None, help="folder (default runs/teach-<date-time>)")
    ap.add_argument("--domain-id", type=int, default=None)
    args = ap.parse_args(argv)
    franka = args.robot != "sim"  # hand-guiding a Franka: franky-sim's or a real one
    franky = args.robot == "franky"
    if args.seconds is None:
        args.seconds = 10.0 if franka else 7.0
    if franka and args.operator != "scripted":
        ap.error("a Franka is guided by hand (franky-sim's scripted one); --operator is for the simulated arm")
    if args.demos < 1 or args.seconds <= 0.0 or args.speed <= 0.0 or args.force_bound <= 0.0:
        ap.error("--demos, --seconds, --speed and --force-bound must be > 0")
    try:
        task = load_task(args.task)
    except ValueError as exc:
        ap.error(str(exc))
    if franka and task.kind != "gear":
        ap.error(f"the Franka cell holds a gear task; {args.task} is a {task.kind} task")
    keyboard = args.operator == "keyboard"
    if keyboard and not sys.stdin.isatty():
        ap.error("--operator keyboard reads keys from a terminal; stdin is not one")
    out = args.out or Path("runs") / time.strftime("teach-%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    overlay = write_task_parameters(args.task, out)
    # an operator works in real time (the scripted one too: it watches the anchor at 50 Hz); a file, last,
    # since the files' /**/ settings would win over -p
    teaching = out / "teach_parameters.yaml"
    if franka:  # zero torque in every episode; the controller's status as often as in simulation
        driver = {"guide": True, "robot_ip": "127.0.0.1" if franky else args.robot}
        if franky:  # a simulator: any kernel, reflexes recovered without a person
            driver |= {"realtime": "ignore", "automatic_error_recovery": True}
        teaching.write_text(yaml.safe_dump({
            "/**/franka_driver": {"ros__parameters": driver},
            "/**/nf_controller": {"ros__parameters": {"status_rate": 50.0}}}))
        from .robot_run import cell_parameters, task_argument

        params = ["--ros-args", "--params-file", str(args.hardware_config), "--params-file", str(teaching),
                  *cell_parameters(args.task)]
    else:
        teaching.write_text(yaml.safe_dump({
            "/**/sim_bridge": {"ros__parameters": {"mode": "realtime"}},
            "/**/nf_controller": {"ros__parameters": {"teleop_speed": float(args.speed), "status_rate": 50.0,
                                                      "idle_mode": "hold", "max_consecutive_misses": 20}}}))
        params = ["--ros-args"] + [a for f in (args.config.resolve().parent / SIM_STACK_PARAMS, args.config, overlay,
                                               teaching) for a in ("--params-file", str(f))]
    domain_id = args.domain_id if args.domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID")
                                                                       or allocate_domain_id())
    env = ros_env(domain_id, sources=False)
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE") if k in env})
    stop_on_signals()
    py = sys.executable
    watch = ("recording /joint_states (", "recording /controller_status (")
    procs = {"recorder": ManagedProcess("recorder", [py, "-m", "nf_bags.record", "-o", str(out / "bag")], env,
                                        out / "logs", watch=watch)}
    sim = None
    if franky:
        from .testing.franky import FrankySim

        (out / "logs").mkdir(parents=True, exist_ok=True)
        try:
            sim = FrankySim(out / "logs" / "franky-sim.log", gear=True, gear_load=True, task=task_argument(args.task))
        except RuntimeError as exc:
            procs["recorder"].stop()
            print(f"[teach] franky-sim: {exc}", file=sys.stderr)
            return 1
    stack = "nf_bringup.franka_stack" if franka else "nf_bringup.sim_stack"
    procs["arm"] = ManagedProcess("arm", [py, "-m", stack, *params], env, out / "logs")
    operator = (HandOperator(sim) if franky else PersonOperator(args.seconds) if franka
                else KeyboardOperator(args.step) if keyboard else ScriptedOperator(task))
    stop = threading.Event()
    if keyboard:
        print("[teach] keys: w/s +x/-x, a/d +y/-y, r/f up/down "
              f"({100 * args.step:g} cm each); {args.seconds:g} s per demonstration", flush=True)
        threading.Thread(target=operator.read_terminal, args=(stop,), daemon=True).start()
    who = ("franky-sim's scripted hand (hand-guiding, zero torque)" if franky else
           f"you, guiding the arm at {args.robot} by hand (zero torque)" if franka else f"the {args.operator} operator")
    print(f"[teach] {args.demos} demonstration(s) of {args.task} by {who} into {out / 'bag'}; "
          f"ROS_DOMAIN_ID {domain_id} (loopback only)", flush=True)
    import rclpy

    code = 0
    rclpy.init()
    try:
        missing = procs["recorder"].wait_for_watched(120.0, [procs["arm"]], texts=watch)
        if missing:
            print(f"[teach] warning: the recorder is not recording {', '.join(missing)} yet", flush=True)
        results = run_demonstrations(task, operator, args.demos, args.seconds, args.first_seed, args.force_bound)
        (out / "demos.json").write_text(json.dumps({"task": args.task, "robot": args.robot,
                                                    "operator": "hand" if franka else args.operator,
                                                    "speed": args.speed, "seconds": args.seconds,
                                                    "demos": results}, indent=1))
        ok = sum(r["success"] for r in results)
        print(f"[teach] {ok}/{len(results)} demonstrations inserted; bag {out / 'bag'}; next: "
              f"python -m nf_bags.fit_demos {out / 'bag'} --config {args.config}", flush=True)
    except (RuntimeError, KeyboardInterrupt) as exc:
        print(f"[teach] stopped: {exc or 'interrupted'}", flush=True)
        code = 1
    finally:
        stop.set()
        rclpy.try_shutdown()
        procs["arm"].stop()
        procs["recorder"].stop()
        if sim is not None:
            sim.stop()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
