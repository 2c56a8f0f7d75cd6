"""``flow_selfcheck``: build a random flow and check the torch flow against the compiled evaluator.

Prints the largest torch-vs-compiled differences of phi, J and the controller force, the
bijectivity error max|phi^-1(phi(x)) - x|, the smallest |det J| and the compiled ``force()`` time
per call; exits 1 if a check exceeds the tolerance 1e-9. Differences are also shown scaled by
max(1, |torch value|) (the bijectivity error by max(1, max|phi|)), and the checks use the scaled
values, so large-weight flows (huge phi and J) are judged by their relative precision.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from nf_controller_node.flow_eval import FlowEvaluator
from nf_core.flow_spec import ACTIVATIONS, FlowArchitecture

from ..flow import init_flow_weights
from ..policy import NFPolicy

TOLERANCE = 1e-9


def _scaled_err(ref: np.ndarray, val: np.ndarray) -> float:
    return float(np.max(np.abs(ref - val) / np.maximum(1.0, np.abs(ref))))


def _random_spd(rng: np.random.Generator, dim: int) -> np.ndarray:
    a = rng.normal(size=(dim, dim))
    return a @ a.T + dim * np.eye(dim)


def time_force(evaluator: FlowEvaluator, x: np.ndarray, xdot: np.ndarray, calls: int) -> tuple[float, float]:
    """(median, best) seconds per ``force`` call over 5 batches of ``calls // 5`` calls each."""
    out = np.empty(evaluator.dim)
    n = max(1, calls // 5)
    per_call = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            evaluator.force(x, xdot, out)
        per_call.append((time.perf_counter() - t0) / n)
    return float(np.median(per_call)), float(min(per_call))


def main(argv: list[str] | None = None) -> int:
    """Run the self-check; returns the process exit code (0 ok, 1 an agreement check failed)."""
    ap = argparse.ArgumentParser(prog="flow_selfcheck", description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--n-flow", type=int, default=2)
    ap.add_argument("--n-hidden", type=int, default=16)
    ap.add_argument("--activation", choices=ACTIVATIONS, default="gelu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0, help="weight scale (>1: large weights)")
    ap.add_argument("--states", type=int, default=200, help="random states to compare")
    ap.add_argument("--time-calls", type=int, default=20000, help="force() calls to time (0: skip)")
    args = ap.parse_args(argv)

    try:
        arch = FlowArchitecture(args.dim, args.n_flow, args.n_hidden, args.activation)
    except ValueError as exc:
        ap.error(str(exc))
    rng = np.random.default_rng(args.seed)
    policy = NFPolicy(
        arch,
        weights=init_flow_weights(arch, rng, args.scale),
        stiffness=_random_spd(rng, arch.dim),
        damping=_random_spd(rng, arch.dim),
        x_ref=rng.normal(scale=0.3, size=arch.dim),
    )
    t0 = time.perf_counter()
    evaluator = FlowEvaluator(policy.to_params())
    build_s = time.perf_counter() - t0

    X = rng.normal(size=(args.states, arch.dim))
    Xd = rng.normal(size=(args.states, arch.dim))
    with torch.no_grad():
        xt = torch.from_numpy(X)
        phi_t, J_t = policy.flow.phi_and_jacobian(xt)
        u_t = policy.mean_force(xt, torch.from_numpy(Xd)).numpy()
        inv_err = float((policy.flow.inverse(phi_t) - xt).abs().max())
        min_det = float(torch.linalg.det(J_t).abs().min())
    phi_t, J_t = phi_t.numpy(), J_t.numpy()
    phi_c = np.empty_like(phi_t)
    J_c = np.empty_like(J_t)
    u_c = np.empty_like(u_t)
    for i in range(args.states):
        evaluator.phi_and_jacobian(X[i], phi_c[i], J_c[i])
        evaluator.force(X[i], Xd[i], u_c[i])

    phi_scale = max(1.0, float(np.abs(phi_t).max()))
    errs = {
        "phi": _scaled_err(phi_t, phi_c),
        "J": _scaled_err(J_t, J_c),
        "force": _scaled_err(u_t, u_c),
        # the inverse subtracts t(c) of the size of phi: judge it relative to that size
        "bijectivity": inv_err / phi_scale,
    }
    rows = [
        ("max |phi torch - compiled|", np.abs(phi_t - phi_c).max(), errs["phi"]),
        ("max |J torch - compiled|", np.abs(J_t - J_c).max(), errs["J"]),
        ("max |force torch - compiled|", np.abs(u_t - u_c).max(), errs["force"]),
        ("max |phi^-1(phi(x)) - x|", inv_err, errs["bijectivity"]),
    ]
    print(f"flow {arch}: {arch.n_params} weights, scale {args.scale}, {args.states} states, seed {args.seed}")
    print(f"evaluator build (incl. compile or cache load): {build_s:.2f} s")
    for label, err, scaled in rows:
        print(f"{label:<32}{float(err):.3e}  (scaled {scaled:.3e})")
    print(f"{'min |det J|':<32}{min_det:.3e}")
    if args.time_calls > 0:
        med, best = time_force(evaluator, X[0], Xd[0], args.time_calls)
        print(f"{'compiled force() per call':<32}{med * 1e6:.2f} us median, {best * 1e6:.2f} us best")
    failed = [name for name, err in errs.items() if not err <= TOLERANCE]
    if not min_det > 0.0:
        failed.append("det J")
    if failed:
        print(f"FAIL: {', '.join(failed)} (tolerance {TOLERANCE:g})")
        return 1
    print("OK")
    return 0


if __name__ == "__main__":
    sys.exit(main())
