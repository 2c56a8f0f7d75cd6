"""The Franka driver's torque loop against franky-sim for N minutes: timing and libfranka exceptions.

franky-sim (MuJoCo FR3, libfranka protocol, 127.0.0.1) is started and stopped by PID; pylibfranka's
torque loop (``franka_driver.loop``) hosts the full controller (a random flow, n_flow=2,
n_hidden=16, x_ref = where the TCP starts, deterministic: the arm holds its pose), exactly as in
``nf_franka_stack`` but without the ROS executor. Measured on our side of the loop (franky-sim
always reports control_command_success_rate 1.0): time from ``readOnce`` returning to ``writeOnce``
returning (p50/p99/p99.9/max), the loop period, ticks later than 1 ms and their longest run,
robot cycles missed between two reads, libfranka exceptions.

    python bench/bench_franka.py --minutes 10        # the target run (do not run it on a shared machine)
    python bench/bench_franka.py --minutes 1         # a short run
    python bench/bench_franka.py --minutes 1 --rt-priority 0    # the loop thread at normal priority

Writes ``bench/results/franka.json``. Targets (issue 14): 0 exceptions, latency p99 <= 150 us and
p99.9 <= 300 us, no run of 3 ticks later than 1 ms.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import sources  # noqa: F401  (the package sources first on sys.path)

from franka_driver.loop import DriverConfig, FrankaDriverLoop
from franka_driver.robot_model import identify
from nf_bringup.testing.franky import HOST, FrankySim
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_controller_node.host import ControllerHost
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.driver_loop import loop_priority
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters
from nf_core.thread_priority import AUTO, open_robot
from nf_core.tick_timing import latency_summary

TARGETS = {"exceptions": 0, "p99_us_max": 150.0, "p999_us_max": 300.0, "late_run_below": 3}

HERE = Path(__file__).resolve().parent


def run(seconds: float, log_dir: Path, rt_priority: int = AUTO) -> dict:
    """Drive the simulated FR3 for ``seconds`` of wall time, the loop thread scheduled as the driver's
    with ``realtime: ignore`` and ``rt_priority`` (auto: SCHED_FIFO 99 if allowed; 0: normal); the
    measurements."""
    try:
        rt_priority = loop_priority(rt_priority, realtime_enforced=False, loop="the torque loop")
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    import pylibfranka as franka

    with FrankySim(log_dir / "franky-sim.log"):
        robot = open_robot(lambda: franka.Robot(HOST, franka.RealtimeConfig.kIgnore))  # main thread: no FIFO
        state = robot.read_once()
        spec = identify("auto", state, robot.load_model()).spec
        arm = spec.arm_model(panda_spec.GEAR_PART)
        loop = ControlLoop(arm, TorqueLawConfig(gravity_compensation=False),
                           LoopConfig(idle_mode="policy", max_consecutive_misses=0), joint_names=spec.joint_names)
        spec.fit_loop(loop)  # the FR3's ranges and limits, as nf_franka_stack does
        host = ControllerHost(loop)
        tcp_arm = spec.arm_model(panda_spec.GEAR_PART)
        x0 = tcp_arm.tcp_position(np.asarray(state.q))
        arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
        weights = np.random.default_rng(0).uniform(-0.25, 0.25, arch.n_params)
        loop.set_policy(PolicyParameters(arch, weights, np.zeros(1), 300.0 * np.eye(3), 40.0 * np.eye(3), x0,
                                         version=1))
        errors = (franka.FrankaException, franka.ControlException, franka.CommandException,
                  franka.NetworkException, franka.RealtimeException, franka.InvalidOperationException)
        driver = FrankaDriverLoop(robot, host, tcp_arm.tcp_position, DriverConfig(keep_timing=True),
                                  franka.Torques, errors, rt_priority=rt_priority)  # scheduled as the node's
        sys.setswitchinterval(1e-4)
        gc.collect()
        t0 = time.monotonic()
        driver.start(logging.getLogger("bench_franka"))
        time.sleep(seconds)
        driver.stop(10.0)
        wall = time.monotonic() - t0
        drift = float(np.linalg.norm(driver.x - x0))
        del robot, driver.robot
    t = driver.timing
    lat, per = latency_summary(t.latency), latency_summary(t.periods)
    return {"seconds": seconds, "wall_s": wall, "arm": spec.kind,
            "loop_scheduling": driver.scheduling, "latency": lat, "period": per,
            **t.counters(), "late_fraction": t.late / max(t.ticks, 1), "exceptions": driver.exceptions,
            "last_error": driver.last_error, "fault": loop.fault, "tcp_drift_mm": drift * 1e3,
            "ticks_per_s": t.ticks / max(wall, 1e-9)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the run (default 10)")
    parser.add_argument("--quick", action="store_true", help="30 s instead")
    parser.add_argument("--rt-priority", type=int, default=AUTO,
                        help="SCHED_FIFO priority of the loop thread: -1 auto (99 if allowed, the driver's default "
                             "with realtime ignore), 0 normal scheduling, 1..99")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "franka.json")
    args = parser.parse_args()
    seconds = 30.0 if args.quick else 60.0 * args.minutes
    args.out.parent.mkdir(parents=True, exist_ok=True)
    result = run(seconds, Path(tempfile.mkdtemp(prefix="bench_franka_")), args.rt_priority)  # franky-sim's log
    lat = result["latency"]
    result["targets"] = TARGETS
    result["met"] = {"exceptions": result["exceptions"] == TARGETS["exceptions"],
                     "p99": lat["p99_us"] <= TARGETS["p99_us_max"], "p999": lat["p999_us"] <= TARGETS["p999_us_max"],
                     "late_run": result["longest_late_run"] < TARGETS["late_run_below"]}
    result["machine"] = {"cpus": os.cpu_count(), "load_1min": os.getloadavg()[0], "python": platform.python_version(),
                         "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.out.write_text(json.dumps(result, indent=1))
    print(f"{result['ticks']} ticks in {result['wall_s']:.0f} s ({result['ticks_per_s']:.0f}/s), arm {result['arm']}, "
          f"loop thread {result['loop_scheduling']}: "
          f"readOnce->writeOnce p50 {lat['p50_us']:.0f} us, p99 {lat['p99_us']:.0f} us, p99.9 {lat['p999_us']:.0f} us, "
          f"max {lat['max_us']:.0f} us; period p99 {result['period']['p99_us']:.0f} us; late {result['late_ticks']} "
          f"(longest run {result['longest_late_run']}); exceptions {result['exceptions']}; load "
          f"{result['machine']['load_1min']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
