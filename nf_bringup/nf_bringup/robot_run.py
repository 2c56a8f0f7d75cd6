"""``run_robot`` (``make run-franka``): learning on the robot path in one command, as ``make run`` is
in simulation. The Franka stack (``nf_franka_stack``: libfranka's torque loop hosting the flow
controller), the bag recorder and the learner, with the cell's goal given once, leave the same run
folder as ``make run`` (learner files, summary.md, learning_curves.png, bag/, logs/).

    run_robot --robot franky                    # franky-sim's FR3 with our gear cell, on 127.0.0.1
    run_robot --robot 172.16.0.2 --goal X Y Z   # a real FR3 / Panda: its FCI address, the measured goal
    run_robot --from-checkpoint runs/gear/checkpoint.pt --iterations 2   # start from a simulation policy

With ``franky`` it starts the simulator first (``nf_bringup.testing.franky --gear --gear-load``, the
shaft's mouth at the driver's default fixture position; goal [0.5, 0, 0.05]) and lets the driver
recover reflexes by itself; on a real arm a reflex or a safe hold waits for a person (the learner
says so and goes on once ``clear_fault`` is called). Ctrl-C stops everything cleanly; the same
``--out`` again resumes from the checkpoint. Each iteration prints the time left.

The learner reads the task file (``--config``, config/gear_learn.yaml) and, from scratch, the arm
settings over it (``--arm-settings``, config/franka_learn.yaml: the cross-entropy step and the settling
spread for an arm's one start; ``none`` leaves them out).

``--from-checkpoint PATH`` starts the learner from a policy learned elsewhere (a simulation run's
``checkpoint.pt``; the learner's ``init_checkpoint``): its flow, S, D and exploration spread with this
cell's goal, a fresh iteration count. The prior evaluated before iteration 1 is then that policy on
the held-out starts (the zero-shot result), the final evaluation the fine-tuned one.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from nf_core.friction import OFF, FrictionRanges

from .processes import ManagedProcess, allocate_domain_id, ros_env, stop_on_signals
from .run_summary import plot_curves, write_summary
from .stack import POLICY_READY, from_checkpoint_args, recorder_ready, wait_for_recorder

# The learner starts once the recorder records these: the Franka stack's controller is composed with
# its driver and publishes no effort_controller/commands (the driver's joint_states carry the torque),
# so waiting for that topic as make run does cost every robot run 120 s before it began.
ROBOT_RECORDED_BEFORE_LEARNING = ("/joint_states", "/rollouts")
ROBOT_RECORDER_READY = recorder_ready(("",), ROBOT_RECORDED_BEFORE_LEARNING)

FRANKY = "franky"
FRANKY_GOAL = (0.5, 0.0, 0.05)  # the gear cell's goal on franky-sim: 2 cm below the shaft's mouth (0.07 m)
DEFAULT_ITERATIONS = 15  # PPO iterations of 15 x 5 s episodes and their reset motions (docs/hardware.md)
# N/m, for a policy learned elsewhere (--from-checkpoint): a simulation without joint friction can
# learn a spring too soft for the arm. On franky-sim's FR3 a simulation policy with a 142 N/m axial
# spring stalled on the shaft top in all 10 starts; lifted to 250 N/m it inserted 10/10
# (docs/hardware.md). From scratch the arm's own rollouts carry its friction: no floor by default.
ARM_STIFFNESS_FLOOR = 250.0
HARDWARE_CONFIG = Path("config/franka.yaml")
ARM_SETTINGS = Path("config/franka_learn.yaml")  # the learner's settings for an arm's one start, over the task file
NONE = "none"
_ITERATION = re.compile(r"iteration\s+(\d+)/(\d+)")
_ROLLOUTS = re.compile(r"rollouts\s+([\d.]+) s")


class Progress:
    """Time left from the learner's iteration lines (its own timing of the whole iteration)."""

    def __init__(self, out=sys.stdout) -> None:
        self.out = out
        self.t_last: float | None = None
        self.durations: list[float] = []

    def __call__(self, line: str) -> None:
        """One line of the learner's output."""
        m = _ITERATION.search(line)
        if not m or "return" not in line:
            return
        now = time.monotonic()
        if self.t_last is not None:
            self.durations.append(now - self.t_last)
        self.t_last = now
        done, total = int(m.group(1)), int(m.group(2))
        first = _ROLLOUTS.search(line)  # before two lines give a wall time: the learner's rollout time
        per = sorted(self.durations)[len(self.durations) // 2] if self.durations else \
            (float(first.group(1)) if first else None)
        if per is not None and done < total:
            left = (total - done) * per
            self.out.write(f"[run] iteration {done}/{total}: {per:.0f} s per iteration, about {left / 60:.0f} min "
                           "left (then the final evaluation)\n")
            self.out.flush()


def robot_commands(args: argparse.Namespace, run_dir: Path, record: bool) -> dict[str, list[str]]:
    """The argv of the Franka stack, the learner and (``record``) the recorder."""
    py = sys.executable
    goal = "[" + ",".join(repr(float(v)) for v in args.goal) + "]"  # floats: a ROS list of one type
    franky = args.robot == FRANKY
    arm = [py, "-m", "nf_bringup.franka_stack", "--ros-args", "--params-file", str(args.hardware_config),
           "-p", f"franka_driver:robot_ip:={'127.0.0.1' if franky else args.robot}",
           "-p", f"franka_driver:goal:={goal}"]
    if franky:  # a simulator: any kernel, and reflexes recovered without a person
        arm += ["-p", "franka_driver:realtime:=ignore", "-p", "franka_driver:automatic_error_recovery:=true"]
    arm += cell_parameters(args.task) if args.task else []
    learner = [py, "-m", "learner_node.node", "--ros-args", "--params-file", str(args.config),
               *(["--params-file", str(args.arm_settings)] if arm_settings_apply(args) else []),
               "-p", f"learner_node:goal:={goal}", "-p", f"learner_node:out_dir:={run_dir / 'learner'}",
               "-p", f"learner_node:iterations:={args.iterations}",
               "-p", f"learner_node:on_safe_hold:={'auto' if franky else 'wait'}",
               "-p", f"learner_node:policy_subscribers:={2 if record else 1}",
               "-p", f"learner_node:stiffness_floor:={float(args.stiffness_floor)!r}",
               *from_checkpoint_args(args.from_checkpoint, run_dir),
               *(["-p", f"task:={task_argument(args.task)}"] if args.task else []), *args.learner_arg]
    state = [py, "-m", "nf_bringup.robot_state", "--ros-args", "--params-file", str(args.config),
             *(["-p", f"task:={task_argument(args.task)}"] if args.task else [])]
    cmds = {"arm": arm, "learner": learner, "state": state}
    if record:
        cmds["recorder"] = [py, "-m", "nf_bags.record", "-o", str(run_dir / "bag")]
    return cmds


def task_argument(task: str) -> str:
    """A task as the nodes get it: a built-in name, or a file's absolute path."""
    from nf_core.task_spec import task_path

    return task if task_path(task).stem == task else str(task_path(task).resolve())


def cell_parameters(task: str) -> list[str]:
    """The Franka stack's cell from a gear task file: the part in the hand, the fixture's mouth, the start
    of the reset motion (over the clamp and pulling up to ``CLAMP_RESET_FORCE``, if the task has one), what
    counts as inside the fixture and as success (overriding the hardware file)."""
    from nf_core.task_spec import load_task

    spec = load_task(task)

    def floats(v) -> str:
        return "[" + ",".join(repr(float(x)) for x in v) + "]"

    return ["-p", f"held_part:={spec.part.text()}",
            "-p", f"franka_driver:fixture_position:={floats(spec.top)}",
            "-p", f"franka_driver:start_position:={floats(spec.start_tcp)}",
            "-p", f"franka_driver:fixture_radius:={spec.lateral_tolerance!r}",
            "-p", f"franka_driver:success_depth:={spec.success_depth!r}",
            *(["-p", f"franka_driver:reset_via:={floats(reset_via(spec).ravel())}",
               "-p", f"franka_driver:reset_force_bound:={CLAMP_RESET_FORCE!r}"] if spec.clamp else [])]


CLAMP_CLEARANCE = 0.15  # m: the TCP's height above a clamp's top while a reset motion passes over it
# N: a reset's pull in a clamp's cell: lifting a gear seated behind a clamp, the orientation spring presses
# its bore against the pin, and the reset must still pull it off (docs/results/teach)
CLAMP_RESET_FORCE = 100.0


def reset_via(spec) -> np.ndarray:
    """A reset motion's way over ``spec``'s clamp (m, base frame): up above the fixture, across above the
    start, at ``CLAMP_CLEARANCE`` over the clamp's top (a straight pull from the fixture would drag the part
    through the jaw)."""
    z = spec.clamp.top + CLAMP_CLEARANCE
    return np.array([[spec.top[0], spec.top[1], z], [spec.start_tcp[0], spec.start_tcp[1], z]])


def arm_settings_apply(args: argparse.Namespace) -> bool:
    """Whether the learner gets ``--arm-settings`` over the task file: from scratch, not from a checkpoint
    (fine-tuning a simulation policy was measured with the task file alone) and not with ``none``."""
    return str(args.arm_settings) != NONE and args.from_checkpoint is None


def learner_only(path: Path) -> str:
    """Why ``path`` cannot be the arm settings ("" if it can): it must hold a ``learner_node`` section only,
    or it would change the other nodes' parameters behind the task file."""
    doc = yaml.safe_load(path.read_text())
    node = doc.get("learner_node") if isinstance(doc, dict) and set(doc) == {"learner_node"} else None
    if not isinstance(node, dict) or not isinstance(node.get("ros__parameters"), dict):
        return f"{path}: the arm settings need one section, learner_node: ros__parameters: ..."
    return ""


def task_shared(config: Path) -> dict:
    """The shared (``/**``) parameters of a task file ({} if it has none)."""
    shared = yaml.safe_load(config.read_text())
    for key in ("/**", "ros__parameters"):
        shared = shared.get(key) if isinstance(shared, dict) else None
    return shared if isinstance(shared, dict) else {}


def simulated_friction(config: Path) -> str:
    """Why ``config`` cannot be the robot run's task file ("" if it can): joint friction ranges
    (``friction_coulomb``/``friction_viscous``) act in the MuJoCo sim only; on an arm the learner would
    record draws the arm never had."""
    shared = task_shared(config)
    try:
        ranges = FrictionRanges(shared.get("friction_coulomb", OFF), shared.get("friction_viscous", OFF))
    except ValueError as exc:
        return f"{config}: {exc}"
    if ranges.enabled:
        return (f"{config} randomizes the simulated joint friction (friction_coulomb {list(ranges.coulomb)}, "
                f"friction_viscous {list(ranges.viscous)}): that is for training in simulation; the arm has its "
                f"own friction. Give the robot run a task file without them (config/gear_learn.yaml) and the "
                f"policy learned with them as --from-checkpoint")
    return ""


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="run_robot", description=__doc__.split("\n\n")[0])
    parser.add_argument("--robot", default=FRANKY,
                        help="'franky' (franky-sim with the gear cell, started here) or the robot's FCI address")
    parser.add_argument("--goal", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="the insertion goal in the robot's base frame, m (franky: 0.5 0 0.05; a real cell: "
                             "measure it)")
    parser.add_argument("--config", type=Path, default=Path("config/gear_learn.yaml"), help="the learner's settings")
    parser.add_argument("--task", default=None, metavar="TASK",
                        help="a gear task file (config/tasks/README.md): the cell (part, fixture, start, success) and, "
                             "unless --goal is given, the goal (its seated pose); on franky the simulated cell is "
                             "built from it. Default: config/franka.yaml's cell")
    parser.add_argument("--hardware-config", type=Path, default=HARDWARE_CONFIG, help="the Franka stack's file")
    parser.add_argument("--arm-settings", type=Path, default=ARM_SETTINGS,
                        help="the learner's settings for an arm's one start, over the task file (from scratch "
                             "only; 'none': the task file alone)")
    parser.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS, help="PPO iterations")
    parser.add_argument("--out", type=Path, default=None, help="run folder (default runs/robot-<date-time>)")
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: from the environment)")
    parser.add_argument("--from-checkpoint", type=Path, default=None, metavar="PATH",
                        help="start the learner from a policy learned elsewhere (e.g. runs/gear/checkpoint.pt of "
                             "train --out runs/gear): its flow, S, D and spread with this cell's goal; the prior "
                             "evaluated first is then the zero-shot result (a run folder's own checkpoint resumes "
                             "instead)")
    parser.add_argument("--stiffness-floor", type=float, default=None, metavar="N_PER_M",
                        help="least learned stiffness S, N/m: every draw, and a --from-checkpoint policy lifted onto "
                             "it (a frictionless simulation can learn a spring the arm's joint friction stalls); "
                             f"default {ARM_STIFFNESS_FLOOR:g} with --from-checkpoint (measured on franky-sim's FR3), "
                             "0 (off) from scratch")
    parser.add_argument("--learner-arg", action="append", default=[], metavar="ARG",
                        help="extra ROS argument for the learner, e.g. -p learner_node:rollouts_per_iter:=5")
    args = parser.parse_args(argv)
    for path in (args.config, args.hardware_config):
        if not path.exists():
            parser.error(f"no such parameters file: {path}")
        yaml.safe_load(path.read_text())  # a broken file fails here, before anything moves
    if arm_settings_apply(args):
        if not args.arm_settings.exists():
            parser.error(f"no such parameters file: {args.arm_settings} (--arm-settings none: the task file alone)")
        problem = learner_only(args.arm_settings)
        if problem:
            parser.error(problem)
        from learner_node.config import TrainConfig, read_yaml_params

        try:  # the learner's own check of the two files together: a typo fails here, before anything moves
            TrainConfig.from_sources(args.config, read_yaml_params(args.arm_settings))
        except (TypeError, ValueError) as exc:
            parser.error(f"{args.arm_settings} over {args.config}: {exc}")
    problem = simulated_friction(args.config)
    if problem:
        parser.error(problem)
    if args.iterations < 1:
        parser.error("--iterations must be >= 1")
    if args.stiffness_floor is None:
        args.stiffness_floor = ARM_STIFFNESS_FLOOR if args.from_checkpoint is not None else 0.0
    if not args.stiffness_floor >= 0.0:
        parser.error("--stiffness-floor must be >= 0 (N/m; 0: off)")
    if args.out is None:
        args.out = Path("runs") / time.strftime("robot-%Y%m%d-%H%M%S")
    try:
        from_checkpoint_args(args.from_checkpoint, args.out)  # a missing file fails here, before anything moves
    except ValueError as exc:
        parser.error(str(exc))
    if args.task is not None:
        from nf_core.task_spec import load_task

        try:
            spec = load_task(args.task)
        except ValueError as exc:
            parser.error(str(exc))
        if spec.kind != "gear":
            parser.error(f"the Franka cell holds a gear task; {args.task} is a {spec.kind} task")
        if args.goal is None:
            args.goal = spec.goal_position.tolist()
    if args.goal is None:
        if args.robot != FRANKY:
            parser.error("a real arm needs --goal X Y Z: the insertion goal measured on its cell")
        args.goal = list(FRANKY_GOAL)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``run_robot``."""
    args = _parse(argv)
    stop_on_signals()
    run_dir = args.out
    run_dir.mkdir(parents=True, exist_ok=True)
    domain_id = args.domain_id if args.domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID")
                                                                      or allocate_domain_id())
    env = ros_env(domain_id, sources=False)
    franky = args.robot == FRANKY
    record = importlib.util.find_spec("nf_bags") is not None
    cmds = robot_commands(args, run_dir, record)
    print(f"[run] run folder {run_dir}, ROS_DOMAIN_ID {domain_id} (loopback only); robot "
          f"{'franky-sim (gear cell)' if franky else args.robot}, goal {args.goal}; {args.iterations} iterations"
          + (f"; the learner starts from {args.from_checkpoint}" if args.from_checkpoint else "")
          + (f"; learner settings {args.config} + {args.arm_settings}" if arm_settings_apply(args) else "")
          + (f"; stiffness floor {args.stiffness_floor:g} N/m" if args.stiffness_floor > 0 else "")
          + "; Ctrl-C stops cleanly, the same --out resumes", flush=True)
    sim = None
    procs: dict[str, ManagedProcess] = {}
    t0 = time.monotonic()
    code: int | None = None
    interrupted = False
    try:
        if franky:
            from .testing.franky import FrankySim

            (run_dir / "logs").mkdir(parents=True, exist_ok=True)
            sim = FrankySim(run_dir / "logs" / "franky-sim.log", gear=True, gear_load=True, task=args.task)
            print("[run] franky-sim up on 127.0.0.1 (FR3, gear cell)", flush=True)
        if record:
            procs["recorder"] = ManagedProcess("recorder", cmds["recorder"], env, run_dir / "logs",
                                               watch=(*ROBOT_RECORDER_READY, POLICY_READY))
        procs["arm"] = ManagedProcess("arm", cmds["arm"], env, run_dir / "logs")
        procs["state"] = ManagedProcess("state", cmds["state"], env, run_dir / "logs")  # for viewers and the bag
        if record:
            wait_for_recorder(procs["recorder"], [procs["arm"]], texts=ROBOT_RECORDER_READY)
        if procs["arm"].running():
            procs["learner"] = ManagedProcess("learner", cmds["learner"], env, run_dir / "logs", on_line=Progress())
            while procs["learner"].running() and procs["arm"].running():
                time.sleep(0.2)
            if not procs["arm"].running():
                print(f"[run] the Franka stack exited (see {run_dir / 'logs' / 'arm.log'}); stopping", flush=True)
        else:
            print(f"[run] the Franka stack did not start (see {run_dir / 'logs' / 'arm.log'})", flush=True)
    except KeyboardInterrupt:
        interrupted = True
        print("[run] interrupted: stopping the nodes (the arm holds, then the torque loop ends)", flush=True)
    finally:
        if "learner" in procs:
            code = procs["learner"].stop()
        for name in ("state", "arm", "recorder"):
            if name in procs:
                procs[name].stop()
        if sim is not None:
            sim.stop()
    wall = time.monotonic() - t0
    plot_curves(run_dir / "learner" / "metrics.json", run_dir / "learning_curves.png",
                f"NF-PPO on the robot path: {'franky-sim' if franky else args.robot}")
    how = f"the Franka stack on {'franky-sim' if franky else args.robot}, real time"
    if arm_settings_apply(args):
        how += f", learner settings of {args.arm_settings} over it"
    summary = write_summary(run_dir, args.config, wall, code, how=how)
    print(f"[run] done in {wall / 60:.1f} min; summary: {summary}", flush=True)
    return 130 if interrupted else (code if code is not None else 1)


if __name__ == "__main__":
    raise SystemExit(main())
