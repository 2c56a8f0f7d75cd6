"""Where a Franka tick's time goes, against franky-sim on 127.0.0.1: our side of the tick
(conversions, ``ControllerHost.tick`` in hold mode, ``Torques``) vs ``writeOnce`` itself; then
``ControllerHost.tick`` running a flow policy after ``readOnce``'s wait, with and without a cache
warm-up (``ControllerHost.warm``) just before ``readOnce`` (interleaved blocks), against the same
tick in a tight loop (the composed realtime sim warms up right before its deadline and gains; here
the ~0.8 ms wait inside ``readOnce`` follows the warm-up, and it gained nothing consistent in four A/B runs, so the
driver does not warm up); then whether
``readOnce`` releases the GIL while it waits for the robot (a counting thread runs during the
torque loop: its rate against the rate while the main thread sleeps).

``--pin``: franky-sim's threads on CPU 0, this loop on CPU 1 (the tick gets a core the simulator
does not use; the GIL-counting phase is skipped, its thread would share that core).

``--compare-pinocchio``: also the tick after ``readOnce`` with the controller's step (flow) and
safe hold (hold) each in one compiled call (the default) and through Pinocchio's bindings and
separate kernels (the arm model's serial chain switched off), 4 interleaved blocks of each of the
four, with the per-block medians.

    PYTHONPATH=bench:$PYTHONPATH python experiments/franka_tick_split.py [--ticks 8000] [--pin] [--compare-pinocchio]

A probe for docs/hardware.md, not a target benchmark (that is ``bench_franka.py``).
"""

from __future__ import annotations

import argparse
import gc
import os
import subprocess
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
import sources  # noqa: F401  (the package sources first on sys.path)

from franka_driver.robot_model import identify
from nf_bringup.testing.franky import HOST, FrankySim
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_controller_node.host import ControllerHost
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters
from nf_core.thread_priority import (
    AUTO,
    apply,
    current_thread_policy,
    open_robot,
    resolve_priority,
)

HERE = Path(__file__).resolve().parent


def _pcts(values: np.ndarray) -> str:
    v = values * 1e6
    return (f"p50 {np.percentile(v, 50):6.1f}  p99 {np.percentile(v, 99):6.1f}  "
            f"p99.9 {np.percentile(v, 99.9):6.1f}  max {v.max():7.1f} us")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=8000)
    parser.add_argument("--pin", action="store_true", help="franky-sim on CPU 0, the torque loop on CPU 1")
    parser.add_argument("--compare-pinocchio", action="store_true",
                        help="also the flow tick with the fused compiled step vs Pinocchio + separate kernels")
    args = parser.parse_args()
    import pylibfranka as franka

    with TemporaryDirectory() as tmp, FrankySim(Path(tmp) / "franky-sim.log") as sim:
        if args.pin:
            subprocess.run(["taskset", "-a", "-p", "-c", "0", str(sim.pid)], check=True, stdout=subprocess.DEVNULL)
            os.sched_setaffinity(0, {1})  # this (main) thread, which runs the torque loop
        robot = open_robot(lambda: franka.Robot(HOST, franka.RealtimeConfig.kIgnore))
        apply(resolve_priority(AUTO, realtime_enforced=False)[0])  # this thread runs the loop: as the driver's
        policy, priority = current_thread_policy()
        print(f"loop thread scheduling: {policy} {priority}", flush=True)
        state = robot.read_once()
        spec = identify("auto", state, robot.load_model()).spec
        loop = ControlLoop(spec.arm_model(panda_spec.GEAR_PART), TorqueLawConfig(gravity_compensation=False),
                           LoopConfig(idle_mode="hold", max_consecutive_misses=0), joint_names=spec.joint_names)
        spec.fit_loop(loop)  # the FR3's ranges and limits, as nf_franka_stack does
        host = ControllerHost(loop)
        perf = time.perf_counter
        n = args.ticks
        ours, write = np.empty(n), np.empty(n)
        count = [0]
        counting = threading.Event()
        done = threading.Event()

        def counter() -> None:
            while not done.is_set():
                if counting.is_set():
                    count[0] += 1

        control = robot.start_torque_control()
        gc.collect()
        for i in range(n):  # phase 1: the split, nothing else running
            st, _ = control.readOnce()
            t0 = perf()
            tau = host.tick(int(st.time.to_sec() * 1e9), np.array(st.q), np.array(st.dq), time.monotonic())
            cmd = franka.Torques(tau.tolist())
            t1 = perf()
            control.writeOnce(cmd)
            ours[i], write[i] = t1 - t0, perf() - t1
        # phase 1b: the flow (bench_franka's random policy) with and without the warm-up before readOnce
        arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
        weights = np.random.default_rng(0).uniform(-0.25, 0.25, arch.n_params)
        x0 = loop.controller.arm.tcp_position(np.asarray(state.q))
        loop.set_policy(PolicyParameters(arch, weights, np.zeros(1), 300.0 * np.eye(3), 40.0 * np.eye(3), x0,
                                         version=1))
        loop.config.idle_mode = "policy"
        flow: dict[str, list[float]] = {"cold": [], "warm": []}
        for b in range(8):
            way = "warm" if b % 2 else "cold"
            for _ in range(n // 8):
                if way == "warm":
                    host.warm()
                st, _ = control.readOnce()
                t0 = perf()
                tau = host.tick(int(st.time.to_sec() * 1e9), np.array(st.q), np.array(st.dq), time.monotonic())
                flow[way].append(perf() - t0)
                control.writeOnce(franka.Torques(tau.tolist()))
        paths: dict[str, list[np.ndarray]] = {}
        if args.compare_pinocchio:  # phase 1c: flow and hold ticks, fused or through Pinocchio
            arm = loop.controller.arm
            chain, chain_args = arm.chain, arm.chain_args
            owned = arm.J, arm.x, arm.R, arm.g  # the Pinocchio path rebinds them to its own arrays
            for b in range(16):
                way = "pinocchio" if b % 2 else "fused"
                loop.config.idle_mode = "policy" if (b // 2) % 2 == 0 else "hold"
                arm.chain, arm.chain_args = (chain, chain_args) if way == "fused" else (None, ())
                if way == "fused":
                    arm.J, arm.x, arm.R, arm.g = owned
                block = np.empty(n // 16)
                for i in range(block.size):
                    st, _ = control.readOnce()
                    t0 = perf()
                    tau = host.tick(int(st.time.to_sec() * 1e9), np.array(st.q), np.array(st.dq), time.monotonic())
                    block[i] = perf() - t0
                    control.writeOnce(franka.Torques(tau.tolist()))
                paths.setdefault(f"{way}, {'flow' if loop.config.idle_mode == 'policy' else 'hold'}", []).append(block)
            loop.config.idle_mode = "policy"
            arm.chain, arm.chain_args = chain, chain_args
            arm.J, arm.x, arm.R, arm.g = owned
        st, _ = control.readOnce()
        q, dq, stamp = np.array(st.q), np.array(st.dq), int(st.time.to_sec() * 1e9)
        control.writeOnce(franka.Torques(host.tau.tolist()))
        tight = np.empty(2000)
        for i in range(tight.size):  # the same tick back to back (one robot state, new stamps)
            t0 = perf()
            host.tick(stamp + i + 1, q, dq, time.monotonic())
            tight[i] = perf() - t0
        st, _ = control.readOnce()  # back to the robot before its watchdog notices the pause
        control.writeOnce(franka.Torques(host.tau.tolist()))
        in_loop = idle = 0.0
        if not args.pin:  # phase 2: the counting thread runs during the torque loop
            thread = threading.Thread(target=counter, daemon=True)
            thread.start()
            counting.set()
            t0, c0 = perf(), count[0]
            for _ in range(n // 4):
                st, _ = control.readOnce()
                tau = host.tick(int(st.time.to_sec() * 1e9), np.array(st.q), np.array(st.dq), time.monotonic())
                control.writeOnce(franka.Torques(tau.tolist()))
            in_loop = (count[0] - c0) / (perf() - t0)
        robot.stop()
        if not args.pin:
            t0, c0 = perf(), count[0]
            time.sleep(2.0)  # baseline: the main thread sleeps (GIL released)
            idle = (count[0] - c0) / (perf() - t0)
            done.set()
            thread.join(2.0)
    skip = min(500, n // 10)
    print(f"our side of the tick  {_pcts(ours[skip:])}")
    print(f"writeOnce             {_pcts(write[skip:])}")
    print(f"flow tick, cold       {_pcts(np.array(flow['cold']))}")
    print(f"flow tick, warm       {_pcts(np.array(flow['warm']))}   (host.warm() before readOnce)")
    print(f"flow tick, tight loop {_pcts(tight[100:])}")
    for way, blocks in paths.items():
        if blocks:
            medians = ", ".join(f"{1e6 * np.median(b):.0f}" for b in blocks)
            print(f"{way + ' tick':21s} {_pcts(np.concatenate(blocks))}   (block p50s {medians})")
    if args.pin:
        print("pinned: franky-sim on CPU 0, the torque loop on CPU 1 (GIL-counting phase skipped)")
        return 0
    print(f"counting thread: {in_loop:,.0f}/s during the torque loop vs {idle:,.0f}/s while the main thread "
          f"sleeps ({in_loop / idle:.0%}): readOnce {'releases' if in_loop > 0.3 * idle else 'does not release'} "
          f"the GIL while it waits")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
