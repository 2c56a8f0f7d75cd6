"""Continuous-time closed loop of the flow controller on a point mass, integrated in numba.

m xddot = u(x, xdot) + F_ext(t). RK4 with sub-steps sized from the current Jacobian, so the
check is of the controller (the theorem is continuous-time), not of a too-coarse integrator.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from nf_controller_node import flow_eval
from nf_controller_node.flow_eval import FlowEvaluator

_force = flow_eval.force_kernel
_potential = flow_eval.potential_kernel
_W_J, _W_POT = flow_eval.WORK_JACOBIAN, flow_eval.WORK_POTENTIAL


@njit(cache=True)
def _accel(x, v, f_ext, mass, wp, layout, code, consts, work, out):
    status = _force(x, v, wp, layout, code, consts, work, out)
    for i in range(x.shape[0]):
        out[i] = (out[i] + f_ext[i]) / mass
    return status


@njit(cache=True)
def simulate(x0, v0, x_ref, mass, dt, n_steps, f_ext, s_max, d_max, settle, wp, layout, code, consts, work):
    """Integrate from (x0, v0); returns (V per step, external work per step, x, v, steps run, status).

    f_ext: (n_steps, dim) external force held over each step; s_max, d_max: largest eigenvalues of S, D.
    Stops early once |x - x_ref| < settle and |v| < settle per second (settle <= 0: never).
    """
    dim = x0.shape[0]
    x, v = x0.copy(), v0.copy()
    V = np.full(n_steps + 1, np.nan)
    W = np.zeros(n_steps + 1)
    k1, k2, k3, k4 = np.empty(dim), np.empty(dim), np.empty(dim), np.empty(dim)
    xs, vs, v2, v3 = np.empty(dim), np.empty(dim), np.empty(dim), np.empty(dim)
    for step in range(n_steps + 1):
        status = _potential(x, wp, layout, code, consts, work)
        if status:
            return V, W, x, v, step, status
        kin, dist, speed = 0.0, 0.0, 0.0
        for i in range(dim):
            kin += 0.5 * mass * v[i] * v[i]
            dist += (x[i] - x_ref[i]) ** 2
            speed += v[i] * v[i]
        V[step] = work[_W_POT, 0] + kin
        if step == n_steps or (settle > 0.0 and dist < settle**2 and speed < settle**2):
            return V, W, x, v, step, 0
        fe = f_ext[step]
        # sub-steps sized from local bounds of the stiffness and damping rates, |J|_F^2 S / m, |J|_F^2 D / m
        status = _accel(x, v, fe, mass, wp, layout, code, consts, work, k1)
        if status:
            return V, W, x, v, step, status
        jn = 0.0
        for i in range(dim * dim):
            jn += work[_W_J, i] ** 2
        rate = max(math.sqrt(jn * s_max / mass), jn * d_max / mass)
        n_sub = min(20000, max(1, int(math.ceil(dt * rate / 0.5))))
        hs = dt / n_sub
        work_done = 0.0
        for _ in range(n_sub):
            _accel(x, v, fe, mass, wp, layout, code, consts, work, k1)
            for i in range(dim):
                xs[i] = x[i] + 0.5 * hs * v[i]
                v2[i] = v[i] + 0.5 * hs * k1[i]
            _accel(xs, v2, fe, mass, wp, layout, code, consts, work, k2)
            for i in range(dim):
                xs[i] = x[i] + 0.5 * hs * v2[i]
                v3[i] = v[i] + 0.5 * hs * k2[i]
            _accel(xs, v3, fe, mass, wp, layout, code, consts, work, k3)
            for i in range(dim):
                xs[i] = x[i] + hs * v3[i]
                vs[i] = v[i] + hs * k3[i]
            status = _accel(xs, vs, fe, mass, wp, layout, code, consts, work, k4)
            if status:
                return V, W, x, v, step, status
            for i in range(dim):
                dx = hs / 6.0 * (v[i] + 2.0 * v2[i] + 2.0 * v3[i] + vs[i])
                work_done += fe[i] * dx  # exact work of a force held constant over the step
                x[i] += dx
                v[i] += hs / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        W[step + 1] = W[step] + work_done
    return V, W, x, v, n_steps, 0


def run(ev: FlowEvaluator, x0: np.ndarray, mass: float, duration: float, dt: float = 1e-3,
        f_ext: np.ndarray | None = None, settle: float = 0.0) -> dict:
    """Simulate the point mass under ``ev`` from rest at x0; returns V, work, final state, status.

    ``settle`` > 0 stops once within ``settle`` metres of x_ref and slower than ``settle`` m/s.
    """
    n = int(round(duration / dt))
    f = np.zeros((n, ev.dim)) if f_ext is None else np.ascontiguousarray(f_ext, dtype=np.float64)
    s_max = float(np.linalg.eigvalsh(ev.stiffness).max())
    d_max = float(np.linalg.eigvalsh(ev.damping).max())
    wp, layout, code, consts, work = ev.kernel_args()
    V, W, x, v, steps, status = simulate(np.asarray(x0, float), np.zeros(ev.dim), ev.x_ref, mass, dt, n, f,
                                         s_max, d_max, settle, wp, layout, code, consts, work)
    return {"V": V[: steps + 1], "work": W[: steps + 1], "x": x, "v": v, "status": status}


def check_flow(args: tuple) -> list[tuple]:
    """Worker entry: one random flow from many starts; returns failures (empty when all pass).

    args = (arch, seed, scale, stiffness, damping, x_ref, mass, n_starts).
    """
    from learner_node.flow import init_flow_weights

    arch, seed, scale, stiffness, damping, x_ref, mass, n_starts = args
    w = init_flow_weights(arch, np.random.default_rng(seed), scale)
    ev = FlowEvaluator(arch, w, stiffness * np.eye(arch.dim), damping * np.eye(arch.dim), x_ref)
    rng = np.random.default_rng(seed + 7)
    failures = []
    for k in range(n_starts):
        r = run(ev, x_ref + rng.uniform(-0.3, 0.3, arch.dim), mass, duration=40.0, dt=0.005, settle=4e-4)
        dist = float(np.linalg.norm(r["x"] - x_ref))
        rise = float(np.max(np.diff(r["V"]))) if r["V"].size > 1 else 0.0
        if r["status"] or dist > 1e-3 or rise > 1e-9 * r["V"][0]:
            failures.append((seed, scale, k, r["status"], dist, rise / r["V"][0]))
    return failures
