"""``run_stack``: the whole stack learning in simulation, as separate processes (the pip
environment has no ``ros2 launch``; ``launch/gear_learning.launch.py`` mirrors this for full
ROS 2 installs).

Starts sim_bridge (lockstep), nf_controller, the bag recorder (when ``nf_bags`` is available)
and, once the recorder subscribes to the arm and rollout topics, learner_node, all with one
parameters file; prefixes and forwards their output, stops them cleanly (SIGINT, then SIGTERM,
then SIGKILL, each by PID) and leaves a run folder::

    runs/<time>/learner/   metrics.csv/json, checkpoint.pt, evaluation.json (learner_node)
    runs/<time>/bag/       rosbag2 MCAP bag of the run (when the recorder is available)
    runs/<time>/learning_curves.png, final_policy.gif, summary.md, logs/<process>.log

Every process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and one ROS_DOMAIN_ID.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO

import yaml

DEFAULT_ITERATIONS = 10  # about 7-8 minutes on the 2-core development machines
# The learner starts only once the recorder subscribes to these (its "recording <topic> (" line):
# the controller's first episode follows the learner's first policy at once, and a recorder still
# discovering topics would miss it (a 0.5 s episode's single rollout chunk was lost that way in CI).
RECORDED_BEFORE_LEARNING = ("/joint_states", "/effort_controller/commands", "/rollouts")
RECORDER_READY = tuple(f"recording {t} (" for t in RECORDED_BEFORE_LEARNING)  # lines to watch for
RECORDER_WAIT_SECONDS = 120.0  # the controller's first start compiles its kernels (~15 s here)


class ManagedProcess:
    """One child process whose output is prefixed and forwarded (and kept in a log file)."""

    def __init__(self, name: str, argv: Sequence[str], env: dict[str, str], log_dir: Path, echo: bool = True,
                 watch: Sequence[str] = ()) -> None:
        self.name = name
        self.argv = list(argv)
        log_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = log_dir / f"{name}.log"
        self._log: IO[str] = self.log_path.open("w")
        self.proc = subprocess.Popen(self.argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1, start_new_session=True)
        self._echo = echo
        self._seen = threading.Condition()
        self._unseen = list(watch)  # watched texts no output line has contained yet (wait_for_watched)
        self._thread = threading.Thread(target=self._forward, name=f"log-{name}", daemon=True)
        self._thread.start()

    def _forward(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._log.write(line)
            self._log.flush()
            if self._unseen:
                with self._seen:
                    self._unseen = [w for w in self._unseen if w not in line]
                    self._seen.notify_all()
            if self._echo:
                sys.stdout.write(f"[{self.name}] {line}" if not line.startswith("[learner]") else line)
                sys.stdout.flush()

    def wait_for_watched(self, timeout: float, alive: Sequence[ManagedProcess] = ()) -> list[str]:
        """Wait until every ``watch`` text given at start has appeared in a line of output; the texts
        still missing (empty on success) when ``timeout`` s pass or this process or one of ``alive`` exits."""
        deadline = time.monotonic() + timeout
        with self._seen:
            while True:
                left = deadline - time.monotonic()
                if not self._unseen or left <= 0 or not all(p.running() for p in (self, *alive)):
                    return list(self._unseen)
                self._seen.wait(timeout=min(left, 0.2))

    @property
    def pid(self) -> int:
        """The child's PID."""
        return self.proc.pid

    def running(self) -> bool:
        """True while the child has not exited."""
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGINT, then SIGTERM, then SIGKILL (by PID), waiting up to ``timeout`` s at each; exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if not self.running():
                break
            os.kill(self.pid, sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                continue
        self._thread.join(timeout=2.0)
        self._log.close()
        return self.proc.poll()


def ros_environment(domain_id: int | None = None) -> dict[str, str]:
    """This process's environment with loopback-only discovery and one domain id."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if domain_id is None:
        domain_id = int(env.get("ROS_DOMAIN_ID") or (100 + os.getpid() % 100))
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def node_commands(config: Path, run_dir: Path, iterations: int, extra: Sequence[str] = ()) -> dict[str, list[str]]:
    """The argv of every process of the stack, keyed by the name used in the log prefix."""
    py = sys.executable
    params = ["--ros-args", "--params-file", str(config)]
    cmds = {
        "sim": [py, "-m", "sim_bridge_node.node", *params],
        "controller": [py, "-m", "nf_controller_node.node", *params, "-p", "nf_controller:idle_mode:=pause",
                       # lockstep: the sim waits for each command, so a slow step is no danger and
                       # must not latch the safe hold (a busy machine would stop the run)
                       "-p", "nf_controller:max_consecutive_misses:=0"],
        "learner": [py, "-m", "learner_node.node", *params, "-p", f"learner_node:out_dir:={run_dir / 'learner'}",
                    "-p", f"learner_node:iterations:={iterations}", *extra],
    }
    if importlib.util.find_spec("nf_bags") is not None:
        cmds["recorder"] = [py, "-m", "nf_bags.record", "-o", str(run_dir / "bag")]
    return cmds


def wait_for_recorder(recorder: ManagedProcess, others: Sequence[ManagedProcess],
                      timeout: float = RECORDER_WAIT_SECONDS) -> bool:
    """Block until the recorder (started with ``watch=RECORDER_READY``) records ``RECORDED_BEFORE_LEARNING``;
    False (with a warning that the bag may miss the first episodes) when it does not within ``timeout`` s
    or a process exited."""
    missing = recorder.wait_for_watched(timeout, others)
    if missing:
        topics = ", ".join(m.split()[1] for m in missing)
        print(f"[stack] warning: the recorder is not recording {topics} after {timeout:.0f} s or a node exited; "
              "starting the learner anyway: the bag may miss the first episodes", flush=True)
        return False
    return True


def write_summary(run_dir: Path, config: Path, wall: float, exit_code: int | None) -> Path:
    """``summary.md``: settings, learning progress, evaluation, timings and the files of the run."""
    learner = run_dir / "learner"
    metrics = json.loads((learner / "metrics.json").read_text()) if (learner / "metrics.json").exists() else []
    evaluation = json.loads((learner / "evaluation.json").read_text()) if (learner / "evaluation.json").exists() \
        else None
    cfg = json.loads((learner / "config.json").read_text()) if (learner / "config.json").exists() else {}
    lines = [f"# Run {run_dir.name}", "", f"Stack run with `{config}` over ROS 2 (lockstep simulation), "
             f"{wall / 60:.1f} min wall time, learner exit code {exit_code}.", ""]
    if cfg:
        lines += [f"Task **{cfg.get('task')}**, policy {cfg.get('policy')}-PPO, sigma_init {cfg.get('sigma_init')} N, "
                  f"seed {cfg.get('seed')}, {cfg.get('rollouts_per_iter')} rollouts of {cfg.get('episode_seconds')} s "
                  "per iteration.", ""]
    if metrics:
        lines += ["| iteration | return | success | final distance (m) | torque (Nm) | rollouts (s) | update (s) |",
                  "|---|---|---|---|---|---|---|"]
        for r in metrics:
            lines.append(f"| {int(r['iteration'])} | {r['return_mean']:.1f} | {r['success_rate']:.2f} | "
                         f"{r['final_distance_mean']:.4f} | {r['torque_norm_mean']:.2f} | {r['rollout_seconds']:.1f} | "
                         f"{r['update_seconds']:.1f} |")
        lines.append("")
    else:
        lines += ["No iteration completed.", ""]
    if evaluation:
        lines += [f"Deterministic controller after iteration {evaluation['iteration']} on "
                  f"{evaluation['episodes']} held-out starts: success {evaluation['success_rate']:.2f}, "
                  f"final distance {evaluation['final_distance_mean']:.4f} m.", ""]
    lines += bag_lines(run_dir / "bag")
    files = sorted(p.relative_to(run_dir) for p in run_dir.rglob("*") if p.is_file())
    shown = [f for f in files if not str(f).startswith(("logs/", "bag/"))]
    lines += ["Files:", ""] + [f"- `{f}`" for f in shown] \
        + (["- `bag/`"] if (run_dir / "bag").exists() else []) + ["- `logs/`", ""]
    path = run_dir / "summary.md"
    path.write_text("\n".join(lines))
    return path


def plot_curves(metrics_path: Path, out: Path, title: str) -> bool:
    """Learning curves of the run (``plots.plot_learning_curves``); False when there is nothing to plot."""
    rows = json.loads(metrics_path.read_text()) if metrics_path.exists() else []
    if not rows:
        return False
    from .plots import plot_learning_curves

    plot_learning_curves([rows], out, title, label="this run")
    return True


def bag_lines(bag: Path) -> list[str]:
    """Lines for ``summary.md`` about the run's bag (topics and message counts), or why there is none."""
    if not bag.exists():
        return ["No bag was recorded (`nf_bags` not importable).", ""]
    try:
        from nf_bags import bagfile

        health = bagfile.scan(bag)
    except Exception as exc:  # a broken bag must not hide the run's results
        return [f"Bag `{bag.name}/` could not be read: {exc}", ""]
    counts = ", ".join(f"{t} {n}" for t, n in sorted(health.counts.items()))
    state = "closed" if health.closed else "NOT closed (see `python -m nf_bags.info --repair`)"
    size = sum(f.stat().st_size for f in bag.glob("*.mcap")) / 1e6
    return [f"Bag `{bag.name}/` ({state}, {size:.1f} MB): {sum(health.counts.values())} messages: {counts}. "
            f"Inspect with `python -m nf_bags.info {bag}`.", ""]


def final_video(run_dir: Path) -> Path | None:
    """GIF of the final deterministic policy from the first held-out start (None without a checkpoint)."""
    checkpoint = run_dir / "learner" / "checkpoint.pt"
    if not checkpoint.exists():
        return None
    import torch

    from .config import TrainConfig
    from .trainer import EVAL_SEED_BASE, Trainer

    state = torch.load(checkpoint, weights_only=True)
    cfg = TrainConfig(**state["config"])
    trainer = Trainer(cfg)
    trainer.load_state_dict(state)
    params = trainer.policy.to_params(version=trainer.iteration)
    out = run_dir / "final_policy.gif"
    from .video import render_policy_gif

    info = render_policy_gif(params, cfg.task, out, start_seed=trainer.runner.start_seed(EVAL_SEED_BASE),
                             seconds=cfg.episode_seconds)
    print(f"[stack] video of the final policy: {out} (depth {info['insertion_depth'] * 1e3:.1f} mm, "
          f"success {info['success']})", flush=True)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``run_stack``."""
    parser = argparse.ArgumentParser(prog="run_stack", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=Path("config/gear.yaml"), help="parameters file of the task")
    parser.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS, help="PPO iterations")
    parser.add_argument("--out", type=Path, default=None, help="run folder (default runs/<date-time>)")
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: from the environment)")
    parser.add_argument("--no-video", action="store_true", help="skip the rendered video of the final policy")
    parser.add_argument("--learner-arg", action="append", default=[], metavar="ARG",
                        help="extra ROS argument for the learner, e.g. -p learner_node:rollouts_per_iter:=5")
    args = parser.parse_args(argv)
    if not args.config.exists():
        parser.error(f"no such parameters file: {args.config}")
    yaml.safe_load(args.config.read_text())  # a broken file fails here, before any process starts
    if args.iterations < 1:
        parser.error("--iterations must be >= 1")
    run_dir = args.out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=True)
    env = ros_environment(args.domain_id)
    print(f"[stack] run folder {run_dir}, ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']} (loopback only); "
          f"{args.iterations} iterations; Ctrl-C stops cleanly and keeps the checkpoint", flush=True)
    cmds = node_commands(args.config, run_dir, args.iterations, args.learner_arg)
    procs: dict[str, ManagedProcess] = {}
    t0 = time.monotonic()
    code: int | None = None
    interrupted = False
    try:
        for name in ("recorder", "sim", "controller"):
            if name in cmds:
                procs[name] = ManagedProcess(name, cmds[name], env, run_dir / "logs",
                                             watch=RECORDER_READY if name == "recorder" else ())
        if "recorder" in procs:
            wait_for_recorder(procs["recorder"], [procs["sim"], procs["controller"]])
        dead = [n for n, p in procs.items() if not p.running()]
        if not dead:
            procs["learner"] = ManagedProcess("learner", cmds["learner"], env, run_dir / "logs")
        while not dead and procs["learner"].running():
            time.sleep(0.2)
            dead = [n for n, p in procs.items() if n != "learner" and not p.running()]
        if dead:
            print(f"[stack] {', '.join(dead)} exited early (see {run_dir / 'logs'}); stopping", flush=True)
    except KeyboardInterrupt:
        interrupted = True
        print("[stack] interrupted: stopping the nodes", flush=True)
    finally:
        if "learner" in procs:
            code = procs["learner"].stop()
        for name in ("controller", "sim", "recorder"):
            if name in procs:
                procs[name].stop()
    wall = time.monotonic() - t0
    if plot_curves(run_dir / "learner" / "metrics.json", run_dir / "learning_curves.png",
                   f"NF-PPO over ROS 2: {args.config.stem}"):
        print(f"[stack] learning curves: {run_dir / 'learning_curves.png'}", flush=True)
    if not args.no_video and not interrupted:
        try:
            final_video(run_dir)
        except Exception as exc:  # a missing GL backend must not hide the run's results
            print(f"[stack] no video: {exc}", flush=True)
    summary = write_summary(run_dir, args.config, wall, code)
    print(f"[stack] done in {wall / 60:.1f} min; summary: {summary}", flush=True)
    return 130 if interrupted else (code or 0)


if __name__ == "__main__":
    raise SystemExit(main())
