"""What bad input costs (issue 16, items 4 and 6): microseconds per rejected vs accepted call of the
controller's and the sim bridge's cores, and the compiled step time per flow size (the basis of
``PolicyLimits.max_flow_params``). Measured and printed, never asserted as timings (shared CI
machines): the tests check only that what is timed is what it claims to be.

Run the measurement: ``python tests/test_hostile_cost.py`` (add ``--sizes`` for the flow sizes).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from collections.abc import Callable

import numpy as np

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_core import panda_spec
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters

NAMES = list(panda_spec.JOINT_NAMES)
Q0 = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])


def _per_call_us(fn: Callable[[int], object], calls: int, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean CPU time of this thread per call (us): on a shared,
    loaded machine, time spent preempted would otherwise swamp the difference being measured."""
    for i in range(min(calls, 200)):
        fn(i)
    means = []
    for _ in range(repeats):
        t0 = time.thread_time_ns()
        for i in range(calls):
            fn(i)
        means.append((time.thread_time_ns() - t0) / calls / 1e3)
    return float(np.median(means))


def _policy(arm: ArmModel, arch: FlowArchitecture | None = None) -> PolicyParameters:
    arch = arch or FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
    bound = 1.0 / np.sqrt(arch.n_hidden)
    weights = np.random.default_rng(0).uniform(-bound, bound, arch.n_params)
    return PolicyParameters(arch, weights, np.zeros(1), 300.0 * np.eye(3), 40.0 * np.eye(3),
                            arm.tcp_position(Q0) + [0.05, 0.0, -0.05], version=1)


def loop_costs(calls: int = 2000) -> dict[str, float]:
    """us per ``on_joint_state`` call: accepted (policy and hold mode) vs rejected kinds. Joint
    states come as the node hands them over (lists), stamps increasing."""
    arm = ArmModel()
    out = {}
    q, dq = Q0.tolist(), [0.0] * 7
    bad = {
        "rejected: NaN velocity": (NAMES, q, [0.0] * 6 + [float("nan")]),
        "rejected: 1e6 rad/s": (NAMES, q, [0.0] * 3 + [1e6] + [0.0] * 3),
        "rejected: q beyond limits": (NAMES, [7.0, *q[1:]], dq),
        "rejected: unknown name": ([*NAMES[:6], "elbow"], q, dq),
        "rejected: 20,000 names": ([f"j{i}" for i in range(20_000)], [0.0] * 20_000, [0.0] * 20_000),
    }
    for mode in ("policy", "hold"):
        loop = ControlLoop(arm, config=LoopConfig(idle_mode=mode))
        loop.set_policy(_policy(arm))
        stamps = itertools.count(1_000_000, 1_000_000)
        out[f"accepted ({mode} mode)"] = _per_call_us(
            lambda i, loop=loop, s=stamps: loop.on_joint_state(NAMES, q, dq, next(s), 0.0), calls)
        assert loop.fault == "" and loop.bad_inputs == 0
    loop = ControlLoop(arm, config=LoopConfig(idle_mode="policy"))
    loop.set_policy(_policy(arm))
    loop.on_joint_state(NAMES, q, dq, 1, 0.0)
    for name, (names, pos, vel) in bad.items():
        before = loop.bad_inputs
        out[name] = _per_call_us(lambda i, n=names, p=pos, v=vel: loop.on_joint_state(n, p, v, 2 + i, 0.0),
                                 calls if len(names) < 100 else max(10, calls // 100))
        assert loop.bad_inputs > before and loop.fault
    before = loop.bad_inputs
    loop.clear_fault()
    loop.on_joint_state(NAMES, q, dq, 10**12, 0.0)  # the new time base
    out["rejected: out of order"] = _per_call_us(
        lambda i: loop.on_joint_state(NAMES, q, dq, 0, 0.0), calls)
    assert loop.bad_inputs > before
    return out


def bridge_costs(calls: int = 2000) -> dict[str, float]:
    """us per ``SimBridge.accept_command``: accepted vs rejected (a physics step is not included)."""
    import array

    from sim_bridge_node.bridge import ACCEPTED, BAD, BridgeConfig, SimBridge
    from sim_bridge_node.env import InsertionEnv

    bridge = SimBridge(InsertionEnv("free"), BridgeConfig(mode="realtime"))
    bridge.reset()
    good = array.array("d", bridge.gravity().tolist())  # what rclpy hands over for float64[]
    kinds = {
        "accepted": (good, ACCEPTED),
        "rejected: NaN": (array.array("d", [0.0] * 6 + [float("nan")]), BAD),
        "rejected: 6 values": (array.array("d", [0.0] * 6), BAD),
        "rejected: 20,000 values": (array.array("d", [0.0] * 20_000), BAD),
    }
    out = {}
    for name, (data, outcome) in kinds.items():
        assert bridge.accept_command(data, 0.0) == outcome
        out[name] = _per_call_us(lambda i, d=data: bridge.accept_command(d, 0.0), calls)
    assert bridge.take_error_report() is not None
    return out


def flow_step_times(sizes: list[tuple[int, int]], calls: int = 3000) -> list[dict]:
    """Compiled controller step (Pinocchio + flow + J + law) per flow size: median and p99 (us)."""
    from nf_controller_node.controller import FlowController
    from nf_controller_node.flow_eval import FlowEvaluator

    arm = ArmModel()
    rng = np.random.default_rng(0)
    qs, dqs = Q0 + rng.normal(0.0, 0.2, (512, 7)), rng.normal(0.0, 0.3, (512, 7))
    rows = []
    for n_flow, n_hidden in sizes:
        arch = FlowArchitecture(dim=3, n_flow=n_flow, n_hidden=n_hidden, activation="gelu")
        ctrl = FlowController(arm, FlowEvaluator.from_params(_policy(arm, arch)))
        for i in range(100):
            ctrl.step(qs[i % 512], dqs[i % 512])
        wall, cpu = np.empty(calls), np.empty(calls)
        for i in range(calls):
            t0, c0 = time.perf_counter_ns(), time.thread_time_ns()
            ctrl.step(qs[i % 512], dqs[i % 512])
            cpu[i], wall[i] = (time.thread_time_ns() - c0) / 1e3, (time.perf_counter_ns() - t0) / 1e3
        rows.append({"n_flow": n_flow, "n_hidden": n_hidden, "n_params": arch.n_params,
                     "median_us": float(np.median(wall)), "p99_us": float(np.percentile(wall, 99)),
                     "cpu_median_us": float(np.median(cpu)), "cpu_p99_us": float(np.percentile(cpu, 99))})
    return rows


# ---------------------------------------------------------------------------- tests (no timing asserted)
def test_rejection_and_acceptance_costs_are_measured(capsys):
    loop, bridge = loop_costs(calls=200), bridge_costs(calls=200)
    with capsys.disabled():
        for name, us in {**loop, **{f"bridge {k}": v for k, v in bridge.items()}}.items():
            print(f"  {name:36s} {us:8.2f} us/call")
    assert all(np.isfinite(v) and v > 0 for v in (*loop.values(), *bridge.values()))


def test_flow_step_time_is_measured_for_a_small_flow():
    (row,) = flow_step_times([(1, 8)], calls=200)
    assert row["n_params"] == FlowArchitecture(3, 1, 8).n_params and row["median_us"] > 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=5000)
    parser.add_argument("--sizes", action="store_true", help="also time the controller step per flow size")
    args = parser.parse_args(argv)
    print("control loop, us (thread CPU time) per on_joint_state call, median of 5 x mean:")
    for name, us in loop_costs(args.calls).items():
        print(f"  {name:36s} {us:8.2f}")
    print("sim bridge, us per accept_command call:")
    for name, us in bridge_costs(args.calls).items():
        print(f"  {name:36s} {us:8.2f}")
    if args.sizes:
        print(f"compiled controller step per flow size ({3000} calls; load average {os.getloadavg()[0]:.1f}):")
        for row in flow_step_times([(2, 16), (4, 32), (2, 64), (4, 64), (8, 64), (4, 128), (8, 128)]):
            print(f"  n_flow={row['n_flow']:2d} n_hidden={row['n_hidden']:4d} weights={row['n_params']:7d}  "
                  f"wall median {row['median_us']:7.1f} p99 {row['p99_us']:7.1f} us; thread CPU median "
                  f"{row['cpu_median_us']:7.1f} p99 {row['cpu_p99_us']:7.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
