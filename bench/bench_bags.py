"""Recording throughput of the 1 kHz stack: sim_bridge (gear, lockstep) + nf_controller (running a
policy) + the recorder as separate processes over DDS. Reports messages/s and MB/s written, CPU
time of the recorder process, and whether any lockstep state or command was dropped (each state
stamp and each command label must be present, no gaps). JSON in bench/results/bags.json.

Usage: python bench/bench_bags.py [--seconds 8] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import sources  # noqa: F401  (the package sources first on sys.path)
from nf_bags import bagfile, reader
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg

from nf_bringup.processes import RosProcess, allocate_domain_id, isolate
from nf_core import qos
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters
from sim_bridge_node.env import InsertionEnv

HERE = Path(__file__).resolve().parent
TOPICS = ["/joint_states", "/effort_controller/commands", "/clock", "/task_status", "/controller_status"]


class Probe:
    """This process's ROS node in its own context, spun until a condition holds."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        isolate(os.environ, domain, sources=False)  # as the children: loopback, UDP
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("bench_bags_probe", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not predicate():
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def policy_msg(x_ref: np.ndarray) -> PolicyParametersMsg:
    """Version 7 of a flow policy with random weights (stable for any), S = 40 I, D = 20 I."""
    arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
    weights = np.random.default_rng(0).uniform(-0.25, 0.25, arch.n_params)
    params = PolicyParameters(arch, weights, np.zeros(1), 40.0 * np.eye(3), 20.0 * np.eye(3),
                              np.asarray(x_ref, float), version=7)
    return params.fill_msg(PolicyParametersMsg())


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process (s), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(seconds: float) -> dict:
    """One measured recording of ``seconds`` of wall time."""
    tmp = Path(tempfile.mkdtemp(prefix="bench_bags_"))
    bag = tmp / "bag"
    domain = allocate_domain_id()
    probe = Probe(domain)
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(bag), "--topics", *TOPICS], domain, tmp / "rec.log")
    sim = RosProcess(["-m", "sim_bridge_node.node", "--ros-args", "-p", "task:=gear", "-p", "mode:=lockstep"],
                     domain, tmp / "sim.log")
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "idle_mode:=policy"], domain,
                     tmp / "ctl.log")
    try:
        probe.node.create_publisher(PolicyParametersMsg, "/policy_parameters", qos.POLICY).publish(
            policy_msg(InsertionEnv("gear").goal_position))
        assert probe.spin_until(lambda: all(f"recording {t} (" in rec.log() for t in TOPICS), 40), rec.log()
        probe.spin_for(1.0)  # warm-up: the stack runs, the recorder has matched everyone
        cpu0, t0 = cpu_seconds(rec.pid), time.monotonic()
        probe.spin_for(seconds)
        cpu1, t1 = cpu_seconds(rec.pid), time.monotonic()
    finally:
        ctl.stop()
        sim.stop()
        probe.spin_for(0.3)
        code = rec.stop()
        probe.close()
    assert code == 0, rec.log()
    health = bagfile.scan(bag)
    rows = list(bagfile.iter_raw(bag))
    wall_ns = [r.log_time for r in rows]
    lo, hi = min(wall_ns), max(wall_ns)
    traj = reader.joint_trajectory(bag)
    commands, _ = reader.commands_by_state(bag)
    stamps = traj.stamp_ns
    state_gaps = int(np.sum(np.diff(stamps) != 1_000_000))
    answered = set(commands)
    missing_commands = int(sum(1 for s in stamps[:-1] if int(s) not in answered))
    size = sum(f.size for f in health.files)
    span = (hi - lo) * 1e-9
    return {
        "seconds_measured": t1 - t0,
        "messages": len(rows), "bag_seconds": span, "file_bytes": size,
        "messages_per_s": len(rows) / span, "mb_per_s": size / span / 1e6,
        "lockstep_steps_per_s": len(stamps) / span,
        "recorder_cpu_fraction": (cpu1 - cpu0) / (t1 - t0),
        "payload_mb_per_s": sum(len(r.data) for r in rows) / span / 1e6,
        "state_gaps": state_gaps, "missing_commands": missing_commands,
        "counts": dict(health.counts), "chunks": sum(f.chunks for f in health.files),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--quick", action="store_true", help="4 s")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "bags.json")
    args = parser.parse_args()
    r = run(4.0 if args.quick else args.seconds)
    r["recorder_cpu_us_per_message"] = r["recorder_cpu_fraction"] * 1e6 / r["messages_per_s"]
    r["no_drops"] = r["state_gaps"] == 0 and r["missing_commands"] == 0
    args.out.parent.mkdir(exist_ok=True)
    args.out.write_text(json.dumps(r, indent=1))
    print(f"recorded {r['messages']} messages in {r['bag_seconds']:.1f} s: {r['messages_per_s']:.0f} msg/s, "
          f"{r['payload_mb_per_s']:.2f} MB/s of CDR payload ({r['mb_per_s']:.2f} MB/s written, zstd), "
          f"lockstep {r['lockstep_steps_per_s']:.0f} steps/s; recorder CPU "
          f"{100 * r['recorder_cpu_fraction']:.0f} % of a core ({r['recorder_cpu_us_per_message']:.0f} us/message); "
          f"drops: {r['state_gaps']} state gaps, {r['missing_commands']} missing commands")
    return 0 if r["no_drops"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
