"""Compiled (numba) batched phi, J = dphi/dx and their vector-Jacobian product, for learning.

``RealNVPFlow.phi_and_jacobian`` and ``NFPolicy.mean_force`` run these kernels inside one
``torch.autograd.Function`` each: for the small flows of this project (dim <= 3, tens of hidden
units) a PPO minibatch takes a few hundred microseconds here, where the same computation as
hundreds of tiny torch ops costs milliseconds of per-op overhead. Arrays are batch-major (the
sample index last and contiguous) so the inner loops run over samples and vectorise. Weights
are read straight from the flat float64 vector in ``flow_spec`` order; :func:`layer_table` gives
each coupling layer's partition and the offsets of its two MLPs in that vector.

Per coupling layer (c = x[cond], z = x[trans]; per MLP p1 = W1 c + b1, h1 = act(p1),
p2 = W2 h1 + b2, h2 = act(p2), out = W3 h2 + b3; g = act', d = act'')::

    WA = W2 diag(g1) W1,  d out / d c = W3 diag(g2) WA
    s = tanh(a), e = exp(s), y[trans] = z e + t
    J[trans] <- diag(e) J[trans] + (diag(z e (1 - s^2)) da/dc + dt/dc) J[cond]

:func:`flow_forward` keeps what the reverse pass needs (each layer's input x and J and the MLP
activations with their first two derivatives); :func:`flow_backward` runs the reverse mode of
exactly these formulas and returns the weight gradient in flow_spec order and the gradient in x.
:func:`force_forward` / :func:`force_backward` add the controller law on top (phi(x_ref) as one
more row of the same batch). The first call compiles (~20 s), later runs load numba's cache.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

from nf_core.flow_spec import FlowArchitecture

MAX_DIM = 3
# Layer table row: [d_cond, d_trans, offset of the s-MLP, offset of the t-MLP, cond[0:3], trans[0:3]].
_T_OFF = 2
_T_COND = 4
_T_TRANS = 7
_T_WIDTH = 10
# Rows of the stored MLP activations: act, act', act'' of both hidden layers.
_H1, _G1, _D1, _H2, _G2, _D2 = range(6)
_N_HID = 6
# backward kernels: may reorder sums (over samples, hidden units) and fuse multiply-adds, nothing
# else (no finite-math or approximate-function assumptions); the results move by rounding only
_REASSOC = {"reassoc", "contract"}

_SQRT_HALF = math.sqrt(0.5)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def _jit(fastmath: bool | set[str] = False) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``numba.njit(cache=True, fastmath=...)``, without caching when no cache directory is writable."""

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        try:
            return numba.njit(cache=True, fastmath=fastmath)(fn)
        except RuntimeError as exc:
            warnings.warn(f"numba caching disabled for {fn.__name__}: {exc}", RuntimeWarning, stacklevel=2)
            return numba.njit(cache=False, fastmath=fastmath)(fn)

    return wrap


def layer_table(arch: FlowArchitecture) -> np.ndarray:
    """int64 (n_layers, 10): d_cond, d_trans, flat offsets of the s- and t-MLP, cond and trans indices."""
    if arch.dim > MAX_DIM:
        raise ValueError(f"the flow kernels support dim <= {MAX_DIM}, got {arch.dim}")
    table = np.zeros((arch.n_layers, _T_WIDTH), dtype=np.int64)
    pos = 0
    for layer in range(arch.n_layers):
        cond, trans = arch.partition(layer)
        table[layer, 0], table[layer, 1] = len(cond), len(trans)
        table[layer, _T_COND : _T_COND + len(cond)] = cond
        table[layer, _T_TRANS : _T_TRANS + len(trans)] = trans
        for m in range(2):
            table[layer, _T_OFF + m] = pos
            pos += sum(math.prod(s) for s in arch.mlp_shapes(len(cond), len(trans)))
    assert pos == arch.n_params
    return table


# ---- forward --------------------------------------------------------------------------------------


@_jit()
def _act(p: float, code: int) -> tuple[float, float, float]:
    """Activation ``code`` (flow_spec order: gelu, tanh, softplus) at p and its first two derivatives."""
    if code == 0:  # exact GELU p Phi(p): act' = Phi + p phi, act'' = phi (2 - p^2)
        cdf = 0.5 * (1.0 + math.erf(p * _SQRT_HALF))
        pdf = _INV_SQRT_2PI * math.exp(-0.5 * p * p)
        return p * cdf, cdf + p * pdf, pdf * (2.0 - p * p)
    if code == 1:
        t = math.tanh(p)
        g = 1.0 - t * t
        return t, g, -2.0 * t * g
    q = math.exp(-abs(p))  # softplus = max(p, 0) + log(1 + e^-|p|), act' = sigmoid
    sig = 1.0 / (1.0 + q) if p >= 0.0 else q / (1.0 + q)
    return max(p, 0.0) + math.log1p(q), sig, sig * (1.0 - sig)


@_jit()
def _mlp_forward(w, off, dc, dt, h, code, cond, y, hid, wa, out, jout, p):
    """MLP at flat offset ``off`` on c = y[cond] (batch-major): out (dt, N), d out/d c (dt, dc, N).

    Keeps act, act', act'' of both hidden layers in hid (6, h, N) and WA (h, dc, N) in wa;
    p (N,) is scratch.
    """
    n = y.shape[1]
    ob1 = off + h * dc
    ow2 = ob1 + h
    ob2 = ow2 + h * h
    ow3 = ob2 + h
    ob3 = ow3 + dt * h
    for i in range(h):
        for s in range(n):
            p[s] = w[ob1 + i]
        for k in range(dc):
            wik = w[off + i * dc + k]
            yk = y[cond[k]]
            for s in range(n):
                p[s] += wik * yk[s]
        for s in range(n):
            a, g, d = _act(p[s], code)
            hid[_H1, i, s] = a
            hid[_G1, i, s] = g
            hid[_D1, i, s] = d
    for i in range(h):
        for s in range(n):
            p[s] = w[ob2 + i]
        for k in range(dc):
            wa[i, k, :] = 0.0
        for m in range(h):
            wim = w[ow2 + i * h + m]
            h1 = hid[_H1, m]
            g1 = hid[_G1, m]
            for s in range(n):
                p[s] += wim * h1[s]
            for k in range(dc):
                wmk = wim * w[off + m * dc + k]
                wak = wa[i, k]
                for s in range(n):
                    wak[s] += wmk * g1[s]
        for s in range(n):
            a, g, d = _act(p[s], code)
            hid[_H2, i, s] = a
            hid[_G2, i, s] = g
            hid[_D2, i, s] = d
    for j in range(dt):
        for s in range(n):
            out[j, s] = w[ob3 + j]
        for k in range(dc):
            jout[j, k, :] = 0.0
        for i in range(h):
            w3 = w[ow3 + j * h + i]
            h2 = hid[_H2, i]
            g2 = hid[_G2, i]
            for s in range(n):
                out[j, s] += w3 * h2[s]
            for k in range(dc):
                wak = wa[i, k]
                jk = jout[j, k]
                for s in range(n):
                    jk[s] += w3 * g2[s] * wak[s]


@_jit()
def _coupling_forward(dc, dt, cond, trans, y, J, out, jout):
    """y, J (batch-major) <- the coupling layer applied in place, given both MLPs' outputs and Jacobians."""
    dim, n = y.shape
    for i in range(dt):
        ti = trans[i]
        for s in range(n):
            sc = math.tanh(out[0, i, s])
            e = math.exp(sc)
            ze = y[ti, s] * e
            y[ti, s] = ze + out[1, i, s]
            coef = ze * (1.0 - sc * sc)
            for col in range(dim):
                acc = e * J[ti, col, s]
                for k in range(dc):
                    acc += (coef * jout[0, i, k, s] + jout[1, i, k, s]) * J[cond[k], col, s]
                J[ti, col, s] = acc


@_jit()
def flow_forward(x, w, table, h, code, keep):
    """phi (N, dim), J (N, dim, dim) of states x (N, dim), and (if ``keep``) what flow_backward needs.

    Returns (phi, J, saved); ``saved`` = (ys, Js, hid, wa, outs, jouts), each layer's input state
    and Jacobian and its MLP intermediates, all batch-major (only the last layer's if not ``keep``).
    """
    n, dim = x.shape
    n_layers = table.shape[0]
    nk = n_layers if keep else 1
    ys = np.empty((n_layers + 1, dim, n))
    Js = np.zeros((n_layers + 1, dim, dim, n))
    hid = np.empty((nk, 2, _N_HID, h, n))
    wa = np.empty((nk, 2, h, MAX_DIM, n))
    outs = np.empty((nk, 2, MAX_DIM, n))
    jouts = np.empty((nk, 2, MAX_DIM, MAX_DIM, n))
    p = np.empty(n)
    for i in range(dim):
        for s in range(n):
            ys[0, i, s] = x[s, i]
            Js[0, i, i, s] = 1.0
    for layer in range(n_layers):
        li = layer if keep else 0
        dc, dt = table[layer, 0], table[layer, 1]
        cond = table[layer, _T_COND : _T_COND + dc]
        trans = table[layer, _T_TRANS : _T_TRANS + dt]
        for m in range(2):
            _mlp_forward(w, table[layer, _T_OFF + m], dc, dt, h, code, cond, ys[layer], hid[li, m], wa[li, m],
                         outs[li, m], jouts[li, m], p)
        ys[layer + 1] = ys[layer]
        Js[layer + 1] = Js[layer]
        _coupling_forward(dc, dt, cond, trans, ys[layer + 1], Js[layer + 1], outs[li], jouts[li])
    phi = np.empty((n, dim))
    jac = np.empty((n, dim, dim))
    for s in range(n):
        for i in range(dim):
            phi[s, i] = ys[n_layers, i, s]
            for j in range(dim):
                jac[s, i, j] = Js[n_layers, i, j, s]
    return phi, jac, (ys, Js, hid, wa, outs, jouts)


# ---- reverse mode ---------------------------------------------------------------------------------


@_jit(_REASSOC)
def _coupling_backward(dc, dt, cond, trans, y, J, out, jout, y_bar, J_bar, out_bar, jout_bar):
    """Reverse of ``_coupling_forward`` at its input y, J: y_bar, J_bar (output cotangents) become the
    input cotangents except for the MLP inputs c; the MLP cotangents go to out_bar, jout_bar."""
    dim, n = y.shape
    for i in range(dt):
        ti = trans[i]
        for s in range(n):
            sc = math.tanh(out[0, i, s])
            q = 1.0 - sc * sc
            e = math.exp(sc)
            z = y[ti, s]
            ze = z * e
            coef = ze * q
            # J_out[ti] = e J[ti] + sum_k M_k J[cond_k],  M_k = coef da_k/dc + dt_k/dc
            e_bar = 0.0
            for col in range(dim):
                e_bar += J_bar[ti, col, s] * J[ti, col, s]
            coef_bar = 0.0
            for k in range(dc):
                ck = cond[k]
                m_bar = 0.0
                m_k = coef * jout[0, i, k, s] + jout[1, i, k, s]
                for col in range(dim):
                    m_bar += J_bar[ti, col, s] * J[ck, col, s]
                    J_bar[ck, col, s] += m_k * J_bar[ti, col, s]
                coef_bar += m_bar * jout[0, i, k, s]
                jout_bar[0, i, k, s] = coef * m_bar
                jout_bar[1, i, k, s] = m_bar
            for col in range(dim):
                J_bar[ti, col, s] *= e
            # y_out[ti] = z e + t,  coef = z e (1 - s^2),  e = exp(s),  s = tanh(a)
            yb = y_bar[ti, s]
            ze_bar = yb + coef_bar * q
            out_bar[1, i, s] = yb
            e_bar += ze_bar * z
            out_bar[0, i, s] = (e_bar * e - 2.0 * coef_bar * ze * sc) * q
            y_bar[ti, s] = ze_bar * e


@_jit(_REASSOC)
def _mlp_backward(w, off, dc, dt, h, cond, y, hid, wa, out_bar, jout_bar, gw, y_bar, scratch):
    """Reverse of ``_mlp_forward``: adds the weight gradient to gw (flat) and d/d c to y_bar[cond].

    scratch: (4 + 2 * MAX_DIM, h, N).
    """
    n = y.shape[1]
    ob1 = off + h * dc
    ow2 = ob1 + h
    ob2 = ow2 + h * h
    ow3 = ob2 + h
    ob3 = ow3 + dt * h
    h2_bar = scratch[0]
    p2_bar = scratch[1]
    h1_bar = scratch[2]
    p1_bar = scratch[3]
    b_bar = scratch[4 : 4 + MAX_DIM]  # d/d B[i, k] = d/d (g2[i] WA[i, k]), as [k, i, s]
    a_bar = scratch[4 + MAX_DIM : 4 + 2 * MAX_DIM]  # then d/d WA, and d/d A[m, k] = g1[m] W1[m, k]
    # out = W3 h2 + b3, jout = W3 B
    h2_bar[:] = 0.0
    b_bar[:dc] = 0.0
    for j in range(dt):
        ob = out_bar[j]
        acc = 0.0
        for s in range(n):
            acc += ob[s]
        gw[ob3 + j] += acc
        for i in range(h):
            w3 = w[ow3 + j * h + i]
            h2 = hid[_H2, i]
            g2 = hid[_G2, i]
            acc = 0.0
            for s in range(n):
                acc += ob[s] * h2[s]
                h2_bar[i, s] += w3 * ob[s]
            for k in range(dc):
                jb = jout_bar[j, k]
                wak = wa[i, k]
                bk = b_bar[k, i]
                for s in range(n):
                    acc += jb[s] * g2[s] * wak[s]
                    bk[s] += w3 * jb[s]
            gw[ow3 + j * h + i] += acc
    # B = diag(g2) WA, h2 = act(p2), g2 = act'(p2): b_bar becomes d/d WA
    for i in range(h):
        g2 = hid[_G2, i]
        d2 = hid[_D2, i]
        pb = p2_bar[i]
        hb = h2_bar[i]
        for s in range(n):
            pb[s] = hb[s] * g2[s]
        for k in range(dc):
            bk = b_bar[k, i]
            wak = wa[i, k]
            for s in range(n):
                pb[s] += bk[s] * wak[s] * d2[s]
                bk[s] *= g2[s]
        acc = 0.0
        for s in range(n):
            acc += pb[s]
        gw[ob2 + i] += acc
    # p2 = W2 h1 + b2, WA = W2 A, A = diag(g1) W1
    h1_bar[:] = 0.0
    a_bar[:dc] = 0.0
    for i in range(h):
        pb = p2_bar[i]
        for m in range(h):
            wim = w[ow2 + i * h + m]
            h1 = hid[_H1, m]
            g1 = hid[_G1, m]
            hb = h1_bar[m]
            acc = 0.0
            for s in range(n):
                acc += pb[s] * h1[s]
                hb[s] += wim * pb[s]
            for k in range(dc):
                bk = b_bar[k, i]
                ak = a_bar[k, m]
                w1 = w[off + m * dc + k]
                for s in range(n):
                    acc += bk[s] * g1[s] * w1
                    ak[s] += wim * bk[s]
            gw[ow2 + i * h + m] += acc
    # h1 = act(p1), g1 = act'(p1), p1 = W1 c + b1
    for m in range(h):
        g1 = hid[_G1, m]
        d1 = hid[_D1, m]
        pb = p1_bar[m]
        hb = h1_bar[m]
        for s in range(n):
            pb[s] = hb[s] * g1[s]
        for k in range(dc):
            w1 = w[off + m * dc + k]
            ak = a_bar[k, m]
            acc = 0.0
            for s in range(n):
                pb[s] += ak[s] * w1 * d1[s]
                acc += ak[s] * g1[s]
            gw[off + m * dc + k] += acc
        acc = 0.0
        for s in range(n):
            acc += pb[s]
        gw[ob1 + m] += acc
        for k in range(dc):
            w1 = w[off + m * dc + k]
            yk = y[cond[k]]
            ybk = y_bar[cond[k]]
            acc = 0.0
            for s in range(n):
                acc += pb[s] * yk[s]
                ybk[s] += w1 * pb[s]
            gw[off + m * dc + k] += acc


@_jit(_REASSOC)
def flow_backward(w, table, h, saved, phi_bar, jac_bar):
    """Vector-Jacobian product of ``flow_forward(..., keep=True)``: (weight gradient (flat), x gradient (N, dim)).

    phi_bar (N, dim) and jac_bar (N, dim, dim) are the cotangents of phi and J; ``saved`` is what
    flow_forward returned.
    """
    ys, Js, hid, wa, outs, jouts = saved
    n, dim = phi_bar.shape
    y_bar = np.empty((dim, n))
    J_bar = np.empty((dim, dim, n))
    for s in range(n):
        for i in range(dim):
            y_bar[i, s] = phi_bar[s, i]
            for j in range(dim):
                J_bar[i, j, s] = jac_bar[s, i, j]
    gw = np.zeros(w.shape[0])
    out_bar = np.empty((2, MAX_DIM, n))
    jout_bar = np.empty((2, MAX_DIM, MAX_DIM, n))
    scratch = np.empty((4 + 2 * MAX_DIM, h, n))
    for layer in range(table.shape[0] - 1, -1, -1):
        dc, dt = table[layer, 0], table[layer, 1]
        cond = table[layer, _T_COND : _T_COND + dc]
        trans = table[layer, _T_TRANS : _T_TRANS + dt]
        _coupling_backward(dc, dt, cond, trans, ys[layer], Js[layer], outs[layer], jouts[layer], y_bar, J_bar,
                           out_bar, jout_bar)
        # the MLPs read c = y[cond], whose cotangent is added to y_bar[cond] (the pass-through part)
        for m in range(2):
            _mlp_backward(w, table[layer, _T_OFF + m], dc, dt, h, cond, ys[layer], hid[layer, m], wa[layer, m],
                          out_bar[m], jout_bar[m], gw, y_bar, scratch)
    x_bar = np.empty((n, dim))
    for s in range(n):
        for i in range(dim):
            x_bar[s, i] = y_bar[i, s]
    return gw, x_bar


# ---- the controller's mean force ------------------------------------------------------------------


@_jit()
def force_forward(x, xdot, x_ref, S, D, w, table, h, code, keep):
    """u = -J^T (S (phi(x) - phi(x_ref)) + D J xdot) for states x, xdot (N, dim); phi(x_ref) in the same pass.

    Returns (u, J, wv, saved): J (N + 1, dim, dim) with x_ref's last, wv = S e + D J xdot (N, dim),
    and flow_forward's saved values for the N + 1 states.
    """
    n, dim = x.shape
    xa = np.empty((n + 1, dim))
    xa[:n] = x
    xa[n] = x_ref
    phi, jac, saved = flow_forward(xa, w, table, h, code, keep)
    u = np.empty((n, dim))
    wv = np.empty((n, dim))
    e = np.empty(dim)
    v = np.empty(dim)
    for s in range(n):
        for i in range(dim):
            e[i] = phi[s, i] - phi[n, i]
            acc = 0.0
            for j in range(dim):
                acc += jac[s, i, j] * xdot[s, j]
            v[i] = acc
        for i in range(dim):
            acc = 0.0
            for j in range(dim):
                acc += S[i, j] * e[j] + D[i, j] * v[j]
            wv[s, i] = acc
        for i in range(dim):
            acc = 0.0
            for j in range(dim):
                acc += jac[s, j, i] * wv[s, j]
            u[s, i] = -acc
    return u, jac, wv, saved


@_jit(_REASSOC)
def force_backward(u_bar, xdot, S, D, jac, wv, w, table, h, saved):
    """Vector-Jacobian product of ``force_forward(..., keep=True)`` for u_bar (N, dim).

    Returns (weight gradient (flat), x gradient (N, dim)); xdot, S, D and x_ref are treated as constants.
    """
    n, dim = u_bar.shape
    phi_bar = np.zeros((n + 1, dim))
    jac_bar = np.zeros((n + 1, dim, dim))
    wv_bar = np.empty(dim)
    v_bar = np.empty(dim)
    for s in range(n):
        # u = -J^T wv
        for j in range(dim):
            acc = 0.0
            for i in range(dim):
                acc -= jac[s, j, i] * u_bar[s, i]
                jac_bar[s, j, i] = -wv[s, j] * u_bar[s, i]
            wv_bar[j] = acc
        # wv = S e + D v,  e = phi(x) - phi(x_ref),  v = J xdot
        for j in range(dim):
            e_bar = 0.0
            vb = 0.0
            for i in range(dim):
                e_bar += S[i, j] * wv_bar[i]
                vb += D[i, j] * wv_bar[i]
            v_bar[j] = vb
            phi_bar[s, j] = e_bar
            phi_bar[n, j] -= e_bar
        for i in range(dim):
            for j in range(dim):
                jac_bar[s, i, j] += v_bar[i] * xdot[s, j]
    gw, x_bar = flow_backward(w, table, h, saved, phi_bar, jac_bar)
    return gw, x_bar[:n]
