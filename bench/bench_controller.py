"""Benchmark of one full 1 kHz controller step against a torch-autograd implementation of it.

One step = ``FlowController.step``: the arm's kinematics (TCP pose, Jacobian, gravity) + flow phi
and Jacobian + controller law + joint torque law with limits, one compiled call. The autograd step
does the same with the arm model's update, phi's Jacobian from ``torch.func.jacrev`` instead of the
compiled analytic evaluator, and the compiled torque law. Writes JSON (``--out``) and prints it.

    python bench/bench_controller.py [--calls N] [--autograd-calls N] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.torque_law import TorqueLawConfig, task_space_torque
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters

Q_HOME = np.array([0.0, -0.12, 0.0, -2.26, 0.0, 2.14, 0.785])


def _stats(samples_us: np.ndarray) -> dict:
    return {
        "calls": int(samples_us.size),
        "median_us": float(np.median(samples_us)),
        "p99_us": float(np.percentile(samples_us, 99)),
        "p999_us": float(np.percentile(samples_us, 99.9)),
        "max_us": float(samples_us.max()),
    }


def _time(fn, n: int, warmup: int) -> np.ndarray:
    for i in range(warmup):
        fn(i)
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        fn(i)
        out[i] = clock() - t0
    return out / 1e3


def _params(arch: FlowArchitecture, seed: int) -> PolicyParameters:
    rng = np.random.default_rng(seed)
    bound = 1.0 / np.sqrt(arch.n_hidden)
    return PolicyParameters(arch=arch, weights=rng.uniform(-bound, bound, arch.n_params), log_std=np.zeros(1),
                            stiffness=4.0 * np.eye(3), damping=np.eye(3), x_ref=np.array([0.5, 0.0, 0.11]))


def _states(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return Q_HOME + rng.normal(0.0, 0.2, (n, 7)), rng.normal(0.0, 0.3, (n, 7))


def bench_architecture(arch: FlowArchitecture, calls: int, autograd_calls: int, seed: int = 0) -> dict:
    """Time the compiled step and the autograd step for one architecture."""
    import torch

    params = _params(arch, seed)
    ctrl = FlowController(ArmModel(), FlowEvaluator.from_params(params))
    qs, dqs = _states(4096, seed)
    mask = 4095

    def fast(i: int) -> None:
        ctrl.step(qs[i & mask], dqs[i & mask])

    fast_us = _time(fast, calls, warmup=2000)
    ctrl.set_posture(Q_HOME, 20.0, 10.0)  # a Franka reset motion's step: the posture spring on
    posture_us = _time(fast, calls, warmup=2000)
    ctrl.set_posture(None)
    ctrl.set_law(TorqueLawConfig(potential_force_bound=60.0))  # make run's bounded pull (gear_learn.yaml)
    bound_us = _time(fast, calls, warmup=2000)
    ctrl.set_law(TorqueLawConfig())
    if ctrl.fault:
        raise RuntimeError(f"controller faulted during the benchmark: {ctrl.fault}")

    from learner_node.flow import RealNVPFlow  # the torch flow used for learning

    torch.set_num_threads(1)
    flow = RealNVPFlow(arch).double()
    flow.load_flat(params.weights)
    S = torch.tensor(params.stiffness)
    D = torch.tensor(params.damping)
    with torch.no_grad():
        phi_ref = flow(torch.tensor(params.x_ref)[None])[0]
    jac = torch.func.jacrev(lambda x: flow(x[None])[0])
    arm, law, tau, u = ctrl.arm, ctrl.law, np.zeros(7), np.zeros(3)
    prev = np.full(7, np.nan)

    def autograd(i: int) -> None:
        q, dq = qs[i & mask], dqs[i & mask]
        arm.update(q, dq)
        x = torch.from_numpy(arm.x.copy())
        xdot = torch.from_numpy(arm.xdot.copy())
        J = jac(x)
        with torch.no_grad():
            e = flow(x[None])[0] - phi_ref
            u[:] = (-(J.T @ (S @ e)) - J.T @ (D @ (J @ xdot))).numpy()
        task_space_torque(arm.J, arm.R, arm.g, dq, u, law.rotation_ref, law.k_rot, law.d_rot, law.joint_damping,
                          law.gravity_compensation, prev, law.torque_limits, law.max_step, tau, np.zeros(7))

    slow_us = _time(autograd, autograd_calls, warmup=50)
    # same state -> same torque: the two steps compute the same law
    ctrl.reset_rate_limit()
    fast(7)
    autograd(7)
    agree = float(np.max(np.abs(ctrl.tau - tau)))
    fast_stats, slow_stats = _stats(fast_us), _stats(slow_us)
    return {
        "arch": {"dim": arch.dim, "n_flow": arch.n_flow, "n_hidden": arch.n_hidden, "activation": arch.activation},
        "compiled_step": fast_stats,
        "compiled_step_posture_spring": _stats(posture_us),
        "compiled_step_force_bound": _stats(bound_us),
        "autograd_step": slow_stats,
        "speedup_median": slow_stats["median_us"] / fast_stats["median_us"],
        "torque_difference_nm": agree,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Time one full controller step (kinematics + flow + J + law) "
                                     "against a torch-autograd step; prints JSON.")
    parser.add_argument("--calls", type=int, default=100_000, help="timed calls of the compiled step")
    parser.add_argument("--autograd-calls", type=int, default=3000, help="timed calls of the autograd step")
    parser.add_argument("--n-flow", type=int, nargs="+", default=[2, 4], help="flow elements to benchmark")
    parser.add_argument("--n-hidden", type=int, default=16)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    results = []
    for n_flow in args.n_flow:
        arch = FlowArchitecture(dim=3, n_flow=n_flow, n_hidden=args.n_hidden, activation="gelu")
        print(f"benchmarking n_flow={n_flow} n_hidden={args.n_hidden}: {args.calls} compiled calls, "
              f"{args.autograd_calls} autograd calls ...", flush=True)
        results.append(bench_architecture(arch, args.calls, args.autograd_calls))
    report = {"benchmark": "controller_step", "machine": platform.machine(), "cpus": os.cpu_count(),
              "load_avg_1min_at_end": os.getloadavg()[0], "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "targets": {"p99_us_max": 30.0, "speedup_min": 50.0}, "results": results}
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
