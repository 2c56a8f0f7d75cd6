"""Regenerate the sample bag ``bags/sample/``: ``python -m nf_bags.sample [--out DIR]``.

Starts sim_bridge (gear, lockstep), nf_controller (pausing between episodes, so nothing steps
before the recorder listens) and the recorder in their own ROS domain, publishes a flow policy
(random weights: stable for any), runs one episode through the ``run_episode`` action and stops
everything cleanly. The result is a small closed bag (about 1.5 s of simulated time at 1 kHz).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BAGS = Path(__file__).resolve().parents[1]
REPO = BAGS.parent
SAMPLE = BAGS / "sample"
TOPICS = ["/joint_states", "/effort_controller/commands", "/clock", "/task_status", "/controller_status",
          "/rollouts", "/policy_parameters", "/diagnostics"]


def _env(domain: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env.pop("ROS_STATIC_PEERS", None)
    paths = [str(REPO / p) for p in ("nf_core", "nf_controller_node", "learner_node", "sim_bridge_node", "bags")]
    env["PYTHONPATH"] = os.pathsep.join([*paths, env.get("PYTHONPATH", "")])
    return env


def _start(args: list[str], domain: int, log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *args], env=_env(domain), stdout=open(log, "w"),
                            stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    return proc.returncode


def record_sample(out: Path, duration: float = 1.5, seed: int = 3, domain: int | None = None) -> Path:
    """Record the sample run into ``out`` (replaced if it exists); returns ``out``."""
    import rclpy
    from nf_msgs.action import RunEpisode
    from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor

    from nf_core import qos
    from nf_core.flow_spec import FlowArchitecture
    from nf_core.policy_params import PolicyParameters
    from nf_core.topics import POLICY_PARAMETERS
    from sim_bridge_node.env import InsertionEnv

    domain = domain if domain is not None else 150 + os.getpid() % 80
    logs = Path(tempfile.mkdtemp(prefix="nf_bags_sample_"))
    tmp_bag = logs / "sample"
    rec = _start(["-m", "nf_bags.record", "-o", str(tmp_bag), "--topics", *TOPICS], domain, logs / "recorder.log")
    sim = _start(["-m", "sim_bridge_node.node", "--ros-args", "-p", "task:=gear", "-p", "mode:=lockstep"],
                 domain, logs / "sim.log")
    # lockstep: the sim waits for every command, so wall-time deadlines mean nothing (a busy
    # machine would latch "consecutive deadline misses" and abort the episode)
    ctl = _start(["-m", "nf_controller_node.node", "--ros-args", "-p", "idle_mode:=pause",
                  "-p", "max_consecutive_misses:=0"], domain, logs / "controller.log")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("nf_bags_sample", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin_until(predicate, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not predicate():
            executor.spin_once(timeout_sec=0.02)
        return bool(predicate())

    try:
        arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
        weights = np.random.default_rng(0).uniform(-0.25, 0.25, arch.n_params)
        params = PolicyParameters(arch, weights, np.array([np.log(2.0)]), 40.0 * np.eye(3), 20.0 * np.eye(3),
                                  InsertionEnv("gear").goal_position, version=1)
        node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY).publish(
            params.fill_msg(PolicyParametersMsg()))
        log = logs / "recorder.log"
        if not spin_until(lambda: all(f"recording {t} (" in log.read_text() for t in TOPICS), 40):
            raise RuntimeError(f"recorder did not subscribe to every topic:\n{log.read_text()}")
        spin_until(lambda: False, 1.0)
        client = ActionClient(node, RunEpisode, "run_episode")
        if not client.wait_for_server(timeout_sec=20):
            raise RuntimeError("no run_episode action server")
        sent = client.send_goal_async(RunEpisode.Goal(policy_version=1, seed=seed, noise_seed=seed, duration=duration))
        if not spin_until(sent.done, 10) or not sent.result().accepted:
            raise RuntimeError("episode goal not accepted")
        done = sent.result().get_result_async()
        if not spin_until(done.done, 120) or not done.result().result.completed:
            raise RuntimeError("episode did not complete")
        spin_until(lambda: False, 1.2)  # a diagnostics report after the episode
    finally:
        _stop(ctl)
        _stop(sim)
        time.sleep(0.3)
        code = _stop(rec)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    if code != 0:
        raise RuntimeError(f"recorder exited with {code}: {(logs / 'recorder.log').read_text()}")
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(tmp_bag), out)
    shutil.rmtree(logs, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    """Record the sample bag and print its summary."""
    parser = argparse.ArgumentParser(prog="python -m nf_bags.sample", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=SAMPLE, help=f"bag directory (default {SAMPLE})")
    parser.add_argument("--duration", type=float, default=1.5, help="episode length, s of simulated time")
    args = parser.parse_args(argv)
    out = record_sample(args.out, args.duration)
    from .bagfile import scan

    print(scan(out).report())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
