"""Regenerate the sample bag ``bags/sample/``: ``python -m nf_bringup.sample_bag [--out DIR]``.

A bringup script (it starts a stack, as ``make run`` does): sim_bridge (gear, lockstep),
nf_controller (pausing between episodes, so nothing steps before the recorder listens) and the
recorder in their own ROS domain; it publishes a flow policy (random weights: stable for any),
runs one episode through the ``run_episode`` action and stops everything cleanly. The result is a
small closed bag (about 1.5 s of simulated time at 1 kHz).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from nf_bringup.processes import REPO

# the checkout's bags/sample (found from the sources or from the install tree inside the checkout)
SAMPLE = REPO / "bags" / "sample" if REPO is not None else Path("sample")
TOPICS = ["/joint_states", "/effort_controller/commands", "/clock", "/task_status", "/controller_status",
          "/rollouts", "/policy_parameters", "/diagnostics"]


def record_sample(out: Path, duration: float = 1.5, seed: int = 3, domain: int | None = None,
                  sim_args: Sequence[str] = ()) -> Path:
    """Record the sample run into ``out`` (replaced if it exists); returns ``out``. ``sim_args``: more
    ``-p`` arguments for the sim (e.g. its joint friction)."""
    import rclpy
    from nf_msgs.action import RunEpisode
    from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor

    from nf_bringup.processes import RosProcess, allocate_domain_id
    from nf_core import qos
    from nf_core.flow_spec import FlowArchitecture
    from nf_core.policy_params import PolicyParameters
    from nf_core.topics import POLICY_PARAMETERS
    from sim_bridge_node.env import InsertionEnv

    domain = domain if domain is not None else allocate_domain_id()
    logs = Path(tempfile.mkdtemp(prefix="nf_bags_sample_"))
    tmp_bag = logs / "sample"
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(tmp_bag), "--topics", *TOPICS], domain, logs / "recorder.log")
    sim = RosProcess(["-m", "sim_bridge_node.node", "--ros-args", "-p", "task:=gear", "-p", "mode:=lockstep",
                      *sim_args], domain, logs / "sim.log")
    # lockstep: the sim waits for every command, so wall-time deadlines mean nothing (a busy
    # machine would latch "consecutive deadline misses" and abort the episode)
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "idle_mode:=pause",
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
        ctl.stop()
        sim.stop()
        time.sleep(0.3)
        code = rec.stop()
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
    parser = argparse.ArgumentParser(prog="python -m nf_bringup.sample_bag", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=SAMPLE, help=f"bag directory (default {SAMPLE})")
    parser.add_argument("--duration", type=float, default=1.5, help="episode length, s of simulated time")
    args = parser.parse_args(argv)
    out = record_sample(args.out, args.duration)
    from nf_bags.bagfile import scan

    print(scan(out).report())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
