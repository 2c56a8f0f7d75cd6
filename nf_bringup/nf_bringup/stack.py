"""``run_stack`` (``make run``): the whole stack learning in simulation (the pip environment has no
``ros2 launch``; ``launch/gear_learning.launch.py`` is the same for full ROS 2 installs).

Starts the arm and its controller (by default composed in one process, ``nf_sim_stack`` in
lockstep; ``--separate``: ``sim_bridge`` and ``nf_controller`` as two processes talking over
topics), the bag recorder (when ``nf_bags`` is available) and, once the recorder subscribes to
the arm and rollout topics, ``learner_node``, all with the same parameters files (``config/sim.yaml``,
then the task file, then any overlays: later files win); prefixes and
forwards their output, stops them cleanly (SIGINT, then SIGTERM, then SIGKILL, each by PID) and
leaves a run folder::

    runs/<time>/learner/   metrics.csv/json, checkpoint.pt, evaluation.json (learner_node)
    runs/<time>/bag/       rosbag2 MCAP bag of the run (when the recorder is available)
    runs/<time>/learning_curves.png, final_policy.gif, summary.md, logs/<process>.log

With ``--arms N`` it starts N composed lockstep arms under the namespaces ``/arm0`` .. ``/arm{N-1}``
(process names ``arm0`` ..), the learner dispatches each iteration's rollouts to all of them, and the
one recorder records every arm's topics. Without ``--arms``: one arm without a namespace.

``--from-checkpoint PATH`` starts the learner from another run's policy (its ``init_checkpoint``): the
prior evaluated first is that policy with this run's goal; the same ``--out`` again resumes the run.

Every process runs in one ROS_DOMAIN_ID with discovery on loopback only (``processes.ros_env``).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import yaml

from .processes import ManagedProcess, allocate_domain_id, ros_env, stop_on_signals
from .run_summary import final_video, plot_curves, write_summary

CHECKPOINT = "checkpoint.pt"  # the learner's (learner_node.trainer.CHECKPOINT), in <run>/learner/
SIM_STACK_PARAMS = "sim.yaml"  # the simulated stack's own settings, beside the task files (config/)
# The learner starts only once the recorder subscribes to these (its "recording <topic> (" line):
# the controller's first episode follows the learner's first policy at once, and a recorder still
# discovering topics would miss it (a 0.5 s episode's single rollout chunk was lost that way in CI).
RECORDED_BEFORE_LEARNING = ("/joint_states", "/effort_controller/commands", "/rollouts")
RECORDER_READY = tuple(f"recording {t} (" for t in RECORDED_BEFORE_LEARNING)  # lines to watch for
# The learner publishes the policy (latched) when it starts: the recorder must pick it up (a bag
# without it cannot be re-simulated); checked after the learner starts, without holding it up.
POLICY_READY = "recording /policy_parameters ("
POLICY_WAIT_SECONDS = 60.0


def arm_namespaces(arms: int) -> list[str]:
    """The namespaces of ``arms`` arms (0: the one arm without a namespace, "")."""
    return [f"/arm{i}" for i in range(arms)] if arms > 0 else [""]


def recorder_ready(namespaces: Sequence[str], topics: Sequence[str] = RECORDED_BEFORE_LEARNING) -> tuple[str, ...]:
    """The recorder's lines to wait for before the learner starts: every arm's ``topics``."""
    return tuple(f"recording {ns}{t} (" for ns in namespaces for t in topics)


def policy_ready(namespaces: Sequence[str]) -> tuple[str, ...]:
    """The recorder's lines that say it records every arm's policy topic."""
    return tuple(f"recording {ns}/policy_parameters (" for ns in namespaces)
RECORDER_WAIT_SECONDS = 120.0  # the controller's first start compiles its kernels (~15 s here)


def stack_configs(configs: Sequence[Path]) -> list[Path]:
    """The parameters files every process gets, in order: the simulated stack's (``config/sim.yaml``,
    beside the task file), then ``configs`` (the task file and its overlays)."""
    return [configs[0].resolve().parent / SIM_STACK_PARAMS, *configs]


def node_commands(configs: Sequence[Path], run_dir: Path, iterations: int | None = None, extra: Sequence[str] = (),
                  composed: bool = True, arms: int = 0, resimulable: bool = False) -> dict[str, list[str]]:
    """The argv of every process of the stack, keyed by the name used in the log prefix; ``arms`` > 0:
    that many arms under ``/arm0`` ..; ``iterations`` None: the files' own; ``resimulable``: the sim
    publishes every step's joint state and command (``monitor_period`` 0), so the bag re-simulates exactly."""
    py = sys.executable
    params = ["--ros-args"] + [arg for path in stack_configs(configs) for arg in ("--params-file", str(path))]
    every_step = ["-p", "sim_bridge:monitor_period:=0.0"] if resimulable else []
    lockstep_controller: list[str] = []  # idle_mode pause, no miss latch: config/sim.yaml's /**/nf_controller
    cmds: dict[str, list[str]] = {}
    for i, ns in enumerate(arm_namespaces(arms)):
        remap = ["-r", f"__ns:={ns}"] if ns else []
        name = f"arm{i}" if ns else "arm"
        # the cell's robot description and transforms, for viewers and the bag (reads the files' task)
        cmds[f"{name}-state" if ns else "state"] = [py, "-m", "nf_bringup.robot_state", *params, *remap]
        if composed:
            cmds[name] = [py, "-m", "nf_bringup.sim_stack", *params, *lockstep_controller, *every_step, *remap]
        else:
            cmds[f"{name}-sim" if ns else "sim"] = [py, "-m", "sim_bridge_node.node", *params, *every_step, *remap]
            cmds[f"{name}-controller" if ns else "controller"] = [
                py, "-m", "nf_controller_node.node", *params, *lockstep_controller, *remap]
    # the arms by name: the learner uses them from the first iteration (discovery would add them too)
    listed = ["-p", "learner_node:arms:=[" + ",".join(f"'{ns}'" for ns in arm_namespaces(arms)) + "]"] if arms else []
    record = importlib.util.find_spec("nf_bags") is not None
    # with a recorder the first episode also waits for its policy subscription (it subscribes only
    # once it sees the learner's publisher), and the learner exits once both subscribers (the
    # controller and the recorder) acknowledged its last policy
    cmds |= {
        "learner": [py, "-m", "learner_node.node", *params,
                    "-p", f"learner_node:out_dir:={run_dir / 'learner'}",
                    "-p", f"learner_node:policy_subscribers:={2 if record else 1}",
                    *(["-p", f"learner_node:iterations:={iterations}"] if iterations is not None else []),
                    *listed, *extra],
    }
    if record:
        cmds["recorder"] = [py, "-m", "nf_bags.record", "-o", str(run_dir / "bag")]
    return cmds


def task_parameters(task: str, run_dir: Path) -> Path:
    """Where ``--task`` puts its parameters overlay (``task`` and ``held_part`` for every node), after
    checking the task. Raises ``ValueError`` (``TaskFileError``) with the reason for a task that cannot be."""
    from nf_core.task_spec import load_task

    load_task(task)
    return run_dir / "task_parameters.yaml"


def write_task_parameters(task: str, run_dir: Path) -> Path:
    """Copy ``task``'s file into the run folder (``task.yaml``: the run keeps the cell it learned) and write
    the overlay that gives every node that file and its part (``task_parameters.yaml``)."""
    from nf_core.task_spec import load_task, task_path

    spec = load_task(task)
    copy = run_dir / "task.yaml"
    copy.write_text(task_path(task).read_text())
    overlay = run_dir / "task_parameters.yaml"
    overlay.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"task": str(copy.resolve()),
                                                                   "held_part": spec.part.text()}}}))
    return overlay


def read_iterations(configs: Sequence[Path]) -> int:
    """The learner's ``iterations`` as the files give it (the last that sets it; else the default)."""
    from learner_node.config import TrainConfig

    return TrainConfig.from_sources(list(configs)).iterations


def from_checkpoint_args(checkpoint: Path | None, run_dir: Path) -> list[str]:
    """The learner's arguments for ``--from-checkpoint``: ``init_checkpoint`` as an absolute path (the
    learner's working directory need not be ours). ``ValueError`` if the file is missing, unless the run
    folder has a checkpoint of its own, which the learner resumes instead."""
    if checkpoint is None:
        return []
    if not checkpoint.is_file() and not (run_dir / "learner" / CHECKPOINT).exists():
        raise ValueError(f"--from-checkpoint {checkpoint}: no such file")
    return ["-p", f"learner_node:init_checkpoint:={checkpoint.resolve()}"]


def wait_for_recorder(recorder: ManagedProcess, others: Sequence[ManagedProcess],
                      timeout: float = RECORDER_WAIT_SECONDS, texts: Sequence[str] = RECORDER_READY) -> bool:
    """Block until the recorder (started watching ``texts``: ``recorder_ready`` of the arms) records
    every arm's ``RECORDED_BEFORE_LEARNING``; False (with a warning that the bag may miss the first
    episodes) when it does not within ``timeout`` s or a process exited."""
    missing = recorder.wait_for_watched(timeout, others, texts=texts)
    if missing:
        topics = ", ".join(m.split()[1] for m in missing)
        print(f"[stack] warning: the recorder is not recording {topics} after {timeout:.0f} s or a node exited; "
              "starting the learner anyway: the bag may miss the first episodes", flush=True)
        return False
    return True


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``run_stack``."""
    parser = argparse.ArgumentParser(prog="run_stack", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, action="append", default=None, metavar="FILE",
                        help="task file, then overlays (repeatable, later files win; default config/gear_learn.yaml); "
                             "config/sim.yaml beside it comes first")
    parser.add_argument("--task", default=None, metavar="TASK",
                        help="the part and cell: a built-in task (gear, peg, gear_clamp) or a task file "
                             "(config/tasks/README.md); default: the parameters file's")
    parser.add_argument("--iterations", type=int, default=None, help="PPO iterations (default: the task file's)")
    parser.add_argument("--out", type=Path, default=None, help="run folder (default runs/<date-time>)")
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: from the environment)")
    parser.add_argument("--no-video", action="store_true", help="skip the rendered video of the final policy")
    parser.add_argument("--learner-arg", action="append", default=[], metavar="ARG",
                        help="extra ROS argument for the learner, e.g. -p learner_node:rollouts_per_iter:=5")
    parser.add_argument("--from-checkpoint", type=Path, default=None, metavar="PATH",
                        help="start the learner from another run's checkpoint.pt (its policy with this run's goal; "
                             "the prior evaluated first is that policy)")
    parser.add_argument("--separate", action="store_true",
                        help="run the sim and the controller as two processes over topics (slower; the path of "
                             "drivers that only speak ros2_control topics) instead of composed in one")
    parser.add_argument("--arms", type=int, default=None, metavar="N",
                        help="N arms under /arm0 .. /arm{N-1}, one learner dispatching to all (default: one arm "
                             "without a namespace)")
    parser.add_argument("--resimulable", action="store_true",
                        help="record every simulated step's joint state and command, so that nf_bags.resim "
                             "re-simulates the bag exactly (config/sim.yaml thins them to every 10 ms); implies "
                             "--separate: the composed lockstep loop steps faster than a recorder takes 1 kHz topics")
    parser.add_argument("--live", action="store_true",
                        help="also serve the live view of the fleet (fleet_view: Foxglove WebSocket on "
                             "ws://127.0.0.1:8765)")
    args = parser.parse_args(argv)
    args.config = args.config or [Path("config/gear_learn.yaml")]
    for path in stack_configs(args.config):
        if not path.exists():
            parser.error(f"no such parameters file: {path}")
        yaml.safe_load(path.read_text())  # a broken file fails here, before any process starts
    iterations = read_iterations(args.config) if args.iterations is None else args.iterations
    if iterations < 1:
        parser.error("--iterations must be >= 1")
    if args.arms is not None and args.arms < 1:
        parser.error("--arms must be >= 1")
    args.arms = args.arms or 0
    if args.resimulable and not args.separate:
        print("[stack] --resimulable: the sim and the controller as two processes (--separate), every step recorded",
              flush=True)
        args.separate = True
    run_dir = args.out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")
    try:
        from_checkpoint = from_checkpoint_args(args.from_checkpoint, run_dir)
    except ValueError as exc:
        parser.error(str(exc))
    task_overlay = None
    if args.task is not None:
        try:
            task_overlay = task_parameters(args.task, run_dir)
        except ValueError as exc:
            parser.error(str(exc))
        args.config.append(task_overlay)
    run_dir.mkdir(parents=True, exist_ok=True)
    if task_overlay is not None:
        write_task_parameters(args.task, run_dir)
    stop_on_signals()
    domain_id = args.domain_id
    if domain_id is None:  # the caller's, else one of its own
        domain_id = int(os.environ.get("ROS_DOMAIN_ID") or allocate_domain_id())
    env = ros_env(domain_id, sources=False)  # the nodes run from the environment's packages (the install tree)
    print(f"[stack] run folder {run_dir}, ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']} (loopback only); "
          f"{iterations} iterations; Ctrl-C stops cleanly and keeps the checkpoint", flush=True)
    cmds = node_commands(args.config, run_dir, args.iterations, [*from_checkpoint, *args.learner_arg],
                         composed=not args.separate, arms=args.arms, resimulable=args.resimulable)
    namespaces = arm_namespaces(args.arms)
    ready, policy_lines = recorder_ready(namespaces), policy_ready(namespaces)
    arm = [n for n in cmds if n not in ("learner", "recorder")]
    if args.live:  # a watcher only: nothing waits for it, and its exit stops nothing
        cmds["view"] = [sys.executable, "-m", "nf_bringup.fleet_view", "--ros-args",
                        "-p", f"run_dir:={run_dir / 'learner'}"]
    print(f"[stack] {'sim and controller as two processes' if args.separate else 'sim and controller composed'}: "
          f"{', '.join(arm)}" + (f" ({args.arms} arms: {', '.join(namespaces)})" if args.arms else ""), flush=True)
    procs: dict[str, ManagedProcess] = {}
    t0 = time.monotonic()
    code: int | None = None
    interrupted = False
    try:
        for name in ("recorder", *arm):
            if name in cmds:
                procs[name] = ManagedProcess(name, cmds[name], env, run_dir / "logs",
                                             watch=(*ready, *policy_lines) if name == "recorder" else ())
        if "view" in cmds:
            procs["view"] = ManagedProcess("view", cmds["view"], env, run_dir / "logs")
        if "recorder" in procs:
            wait_for_recorder(procs["recorder"], [procs[n] for n in arm], texts=ready)
        dead = [n for n, p in procs.items() if not p.running() and n != "view"]
        if not dead:
            procs["learner"] = ManagedProcess("learner", cmds["learner"], env, run_dir / "logs")
            missing = procs["recorder"].wait_for_watched(POLICY_WAIT_SECONDS, [procs["learner"]], texts=policy_lines) \
                if "recorder" in procs else []
            if missing:
                topics = ", ".join(m.split()[1] for m in missing)
                print(f"[stack] warning: the recorder is not recording {topics} {POLICY_WAIT_SECONDS:.0f} s "
                      "after the learner started: the bag may not hold the policies", flush=True)
        while not dead and procs["learner"].running():
            time.sleep(0.2)
            dead = [n for n, p in procs.items() if n not in ("learner", "view") and not p.running()]
        if dead:
            print(f"[stack] {', '.join(dead)} exited early (see {run_dir / 'logs'}); stopping", flush=True)
    except KeyboardInterrupt:
        interrupted = True
        print("[stack] interrupted: stopping the nodes", flush=True)
    finally:
        if "learner" in procs:
            code = procs["learner"].stop()
        for name in (*reversed(arm), "recorder", "view"):
            if name in procs:
                procs[name].stop()
    wall = time.monotonic() - t0
    if plot_curves(run_dir / "learner" / "metrics.json", run_dir / "learning_curves.png",
                   f"NF-PPO over ROS 2: {' + '.join(c.stem for c in args.config)}"):
        print(f"[stack] learning curves: {run_dir / 'learning_curves.png'}", flush=True)
    if not args.no_video and not interrupted:
        try:
            final_video(run_dir)
        except Exception as exc:  # a missing GL backend must not hide the run's results
            print(f"[stack] no video: {exc}", flush=True)
    summary = write_summary(run_dir, args.config[0], wall, code, composed=not args.separate, arms=args.arms)
    print(f"[stack] done in {wall / 60:.1f} min; summary: {summary}", flush=True)
    return 130 if interrupted else (code or 0)


if __name__ == "__main__":
    raise SystemExit(main())
