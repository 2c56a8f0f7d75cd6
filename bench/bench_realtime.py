"""Benchmark of the realtime path: sim_bridge at 1 kHz wall clock + nf_controller, separate processes.

The sim (the driver) times every state-to-command round trip: from publishing joint state k
to receiving the command that answers it (sensing-to-command latency, both DDS hops and the
controller included), and counts a deadline miss whenever that command has not arrived by the
next 1 ms tick. The longest run of consecutive misses is the number that matters for a real
Franka, which aborts at about 20.

Two phases in the same run, each with fresh processes (own ROS_DOMAIN_ID, loopback only):
  1. baseline: the sim answered by ``realtime_echo.py`` (same runtime, no controller work);
  2. controller: the sim answered by nf_controller running the gear task's iteration-0 policy.
Writes ``bench/results/realtime.json``. Targets (issue #6): p99 <= 0.5 ms; never 20 misses in a row.
Usage: python bench/bench_realtime.py [--seconds 600] [--baseline-seconds 60] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CONFIG = REPO / "config" / "gear.yaml"
TARGET_P99_US = 500.0
ABORT_RUN = 20  # consecutive missed cycles at which a Franka stops


def _env(domain: int) -> dict[str, str]:
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONUNBUFFERED="1")


def _stop(proc: subprocess.Popen, timeout: float = 15.0) -> None:
    """SIGINT, then SIGKILL if it does not exit (only our own child, by PID)."""
    if proc.poll() is None:
        proc.send_signal(2)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _policy_publisher(domain: int):
    """A node in this process that latches the gear task's iteration-0 policy (version 1)."""
    import rclpy
    from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer
    from nf_controller_node import topics

    params = Trainer(TrainConfig.from_sources(CONFIG, {"rollouts_per_iter": 1})).policy.to_params(version=1)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("bench_policy", context=context)
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = node.create_publisher(PolicyParametersMsg, topics.POLICY_PARAMETERS, qos)
    pub.publish(params.fill_msg(PolicyParametersMsg()))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return context, node, executor


def run_phase(name: str, seconds: float, domain: int, workdir: Path, log_dir: Path) -> dict:
    """One phase: start sim + responder, wait for the first answers, run ``seconds``, stop, read the log."""
    log = workdir / f"{name}.npy"
    sim_args = ["-m", "sim_bridge_node.node", "--ros-args", "--params-file", str(CONFIG),
                "-p", "sim_bridge:mode:=realtime", "-p", f"sim_bridge:response_log:={log}"]
    if name == "baseline":
        sim_args += ["-p", "sim_bridge:driver_gravity_compensation:=true"]
        responder = [str(HERE / "realtime_echo.py")]
    else:
        responder = ["-m", "nf_controller_node.node", "--ros-args", "--params-file", str(CONFIG),
                     "-p", "nf_controller:idle_mode:=policy"]
    env = _env(domain)
    outs = {k: open(log_dir / f"{name}_{k}.log", "w") for k in ("sim", "responder")}
    ros = None
    # Responder first, so it is compiled and subscribed before the first tick.
    resp = subprocess.Popen([sys.executable, *responder], env=env, stdout=outs["responder"], stderr=subprocess.STDOUT)
    sim = None
    try:
        if name != "baseline":
            ros = _policy_publisher(domain)
        time.sleep(3.0 if name == "baseline" else 8.0)
        sim = subprocess.Popen([sys.executable, *sim_args], env=env, stdout=outs["sim"], stderr=subprocess.STDOUT)
        time.sleep(5.0)  # discovery, first answers, policy swap
        print(f"[{name}] running {seconds:.0f} s", flush=True)
        t0 = time.monotonic()
        next_report = t0 + 60.0
        while time.monotonic() - t0 < seconds:
            if sim.poll() is not None or resp.poll() is not None:
                raise RuntimeError(f"{name}: a process exited early (logs in {log_dir})")
            if ros is not None:
                ros[2].spin_once(timeout_sec=0.2)
            else:
                time.sleep(0.2)
            if time.monotonic() >= next_report:
                print(f"[{name}] {time.monotonic() - t0:.0f}/{seconds:.0f} s, load {os.getloadavg()[0]:.2f}",
                      flush=True)
                next_report += 60.0
    finally:
        if sim is not None:
            _stop(sim)  # the sim first: it writes the log, and no misses are counted for a stopping responder
        _stop(resp)
        if ros is not None:
            ros[1].destroy_node()
            ros[0].try_shutdown()
        for f in outs.values():
            f.close()
    summary_file = log.with_suffix(".json")
    if not summary_file.exists():
        raise RuntimeError(f"{name}: the sim wrote no response log (see {log_dir})")
    summary = json.loads(summary_file.read_text())
    lat = np.load(log)
    summary["latency_samples"] = int(lat.size)
    summary["miss_fraction"] = summary["deadline_misses"] / max(summary["states"], 1)
    print(f"[{name}] {lat.size} answers: median {summary['p50_us']:.0f} us, p99 {summary['p99_us']:.0f} us, "
          f"p99.9 {summary['p99_9_us']:.0f} us, max {summary['max_us']:.0f} us; misses {summary['deadline_misses']} "
          f"({100 * summary['miss_fraction']:.3f} %), longest run {summary['longest_miss_run']}, "
          f"command timeouts {summary['command_timeouts']}", flush=True)
    for run in summary.get("long_miss_runs", []):
        print(f"[{name}]   {run['misses']} misses in a row at {run['at_s']:.1f} s", flush=True)
    return summary


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="length of the controller phase (s)")
    parser.add_argument("--baseline-seconds", type=float, default=60.0, help="length of the baseline phase (s)")
    parser.add_argument("--quick", action="store_true", help="30 s controller, 10 s baseline")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "realtime.json")
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.baseline_seconds = 30.0, 10.0
    domain = 100 + os.getpid() % 50
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        log_dir = args.out.parent / "realtime_logs"
        log_dir.mkdir(parents=True, exist_ok=True)
        baseline = run_phase("baseline", args.baseline_seconds, domain, Path(tmp), log_dir)
        controller = run_phase("controller", args.seconds, domain + 1, Path(tmp), log_dir)
    result = {
        "benchmark": "realtime sensing-to-command latency at 1 kHz (sim_bridge realtime + responder, "
                     "separate processes)",
        "command": "python bench/bench_realtime.py" + (" --quick" if args.quick else ""),
        "seconds": {"controller": args.seconds, "baseline": args.baseline_seconds},
        "baseline_echo": baseline,
        "controller": controller,
        "targets": {"p99_us_max": TARGET_P99_US, "longest_miss_run_below": ABORT_RUN},
        "p99_met": controller["p99_us"] <= TARGET_P99_US,
        "miss_run_met": controller["longest_miss_run"] < ABORT_RUN,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                    "load_before": load_before, "load_after": os.getloadavg()},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    met = {True: "met", False: "NOT met"}
    print(f"p99 {controller['p99_us']:.0f} us (target <= {TARGET_P99_US:.0f}: {met[result['p99_met']]}); "
          f"longest miss run {controller['longest_miss_run']} (target < {ABORT_RUN}: "
          f"{met[result['miss_run_met']]}); written {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
