"""Fast float64 evaluator of the flow controller for the 1 kHz loop (numba, one compiled call per method).

Follows the one definition in ``flow_spec``; a test holds it equal to the torch flow of
``learner_node.flow`` to 1e-9. :func:`pack` rearranges the flat weights once into one block
per MLP (a 3-D array, every row contiguous over hidden units) plus an int64 partition table;
every call then runs a single compiled kernel over preallocated buffers.

Controller law (``force``)::

    u = -J(x)^T S [phi(x) - phi(x_ref)] - J(x)^T D J(x) xdot
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

from nf_core.flow_spec import ACTIVATION_CODES, FlowArchitecture
from nf_core.policy_params import PolicyParameters

MAX_DIM = 3

# Packed MLP block ``wp[2 * layer + (0: s, 1: t)]``, shape (h + 3 + 2 * MAX_DIM, max(h, MAX_DIM)),
# row offsets relative to h: rows 0..h-1 hold W2^T (row m = weights leaving hidden unit m), then
_R_B1 = 0  # b1
_R_B2 = 1  # b2
_R_W1T = 2  # W1^T, one row per input k
_R_W3 = 2 + MAX_DIM  # W3, one row per output j
_R_B3 = 2 + 2 * MAX_DIM  # b3 (first d_out entries)
_PACK_EXTRA_ROWS = 3 + 2 * MAX_DIM

# Partition table row: [d_cond, d_trans, cond[0:MAX_DIM], trans[0:MAX_DIM]].
_L_COND = 2
_L_TRANS = _L_COND + MAX_DIM
LAYOUT_WIDTH = _L_TRANS + MAX_DIM

# Rows of the 2-D work buffer (width max(h, MAX_DIM**2)).
_W_Y = 0  # phi (dim)
_W_J = 1  # J, row-major (dim * dim)
_W_C = 2  # conditioning inputs of the current layer
_W_A = 3  # raw s-MLP output
_W_T = 4  # t-MLP output
_W_JA = 5  # d a / d c, (d_trans, d_cond) row-major
_W_JT = 6  # d t / d c
_W_E = 7  # phi(x) - phi(x_ref)
_W_V = 8  # J xdot
_W_WV = 9  # S e + D J xdot
_W_POT = 10  # potential value in column 0
_W_H1 = 11  # first hidden layer output
_W_H2 = 12  # second hidden layer output
_W_G2 = 13  # its activation derivative
_W_P = 14  # second layer pre-activation
_W_AK = 15  # A[k, m] = act'(p1[m]) W1[m, k], MAX_DIM rows
_W_BK = _W_AK + MAX_DIM  # B[k, i] = sum_m W2[i, m] A[k, m], MAX_DIM rows
_W_ROWS = _W_BK + MAX_DIM

_SQRT_HALF = math.sqrt(0.5)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)

_OK, _BAD_X, _BAD_XDOT, _BAD_OUT = 0, 1, 2, 3
_F64 = np.dtype(np.float64)


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True)``, falling back to no caching when no cache directory is writable."""
    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
        warnings.warn(f"numba caching disabled for {fn.__name__}: {exc}", RuntimeWarning, stacklevel=2)
        return numba.njit(cache=False)(fn)


def work_shape(arch: FlowArchitecture) -> tuple[int, int]:
    """Shape of the float64 scratch buffer the kernels need for ``arch``."""
    return (_W_ROWS, max(arch.n_hidden, MAX_DIM * MAX_DIM))


def pack(arch: FlowArchitecture, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pack flat weights (flow_spec order) for the kernels: (MLP blocks, partition table).

    Blocks: float64 (2 * n_layers, h + 9, max(h, 3)); block ``2 * layer + m`` (m = 0: s-MLP,
    1: t-MLP) holds W2^T in rows 0..h-1, then b1, b2, W1^T (3 rows), W3 (3 rows), b3, zero
    padded. Table: int64 (n_layers, 8) with d_cond, d_trans, cond and trans indices.
    """
    flat = np.asarray(weights, dtype=np.float64).reshape(-1)
    if flat.size != arch.n_params:
        raise ValueError(f"weights: expected {arch.n_params} values, got {flat.size}")
    h = arch.n_hidden
    blocks = np.zeros((2 * arch.n_layers, h + _PACK_EXTRA_ROWS, max(h, MAX_DIM)))
    layout = np.zeros((arch.n_layers, LAYOUT_WIDTH), dtype=np.int64)
    pos = 0
    for layer in range(arch.n_layers):
        cond, trans = arch.partition(layer)
        dc, dt = len(cond), len(trans)
        layout[layer, 0], layout[layer, 1] = dc, dt
        layout[layer, _L_COND : _L_COND + dc] = cond
        layout[layer, _L_TRANS : _L_TRANS + dt] = trans
        for m in range(2):
            arrays = []
            for shape in arch.mlp_shapes(dc, dt):
                size = int(np.prod(shape))
                arrays.append(flat[pos : pos + size].reshape(shape))
                pos += size
            W1, b1, W2, b2, W3, b3 = arrays
            blk = blocks[2 * layer + m]
            blk[:h, :h] = W2.T
            blk[h + _R_B1, :h] = b1
            blk[h + _R_B2, :h] = b2
            blk[h + _R_W1T : h + _R_W1T + dc, :h] = W1.T
            blk[h + _R_W3 : h + _R_W3 + dt, :h] = W3
            blk[h + _R_B3, :dt] = b3
    assert pos == arch.n_params
    return blocks, layout


# ---- compiled kernels ---------------------------------------------------------------------------


@_jit
def _act(p: float, code: int, jac: bool) -> tuple[float, float]:
    """Activation ``code`` at ``p`` and (if ``jac``, else 0) its derivative, sharing the costly calls."""
    if code == 0:  # exact GELU: p * Phi(p)
        cdf = 0.5 * (1.0 + math.erf(p * _SQRT_HALF))
        der = cdf + p * _INV_SQRT_2PI * math.exp(-0.5 * p * p) if jac else 0.0
        return p * cdf, der
    if code == 1:  # tanh via expm1: as accurate as libm's tanh here, and about 3x cheaper
        em = math.expm1(-2.0 * abs(p))
        t = -em / (2.0 + em)
        if p < 0.0:
            t = -t
        return t, 1.0 - t * t
    q = math.exp(-abs(p))  # softplus = max(p, 0) + log1p(e^-|p|), derivative sigmoid(p)
    if jac:
        der = 1.0 / (1.0 + q) if p >= 0.0 else q / (1.0 + q)
    else:
        der = 0.0
    return max(p, 0.0) + math.log1p(q), der


@_jit
def _mlp(wp, mi, dc, dout, h, code, jac, work, out_row, jout_row):
    """MLP block ``mi`` on work[_W_C]; output to work[out_row], its Jacobian (dout, dc) to work[jout_row]."""
    for i in range(h):
        acc = wp[mi, h + _R_B1, i]
        for k in range(dc):
            acc += wp[mi, h + _R_W1T + k, i] * work[_W_C, k]
        a, g = _act(acc, code, jac)
        work[_W_H1, i] = a
        if jac:
            for k in range(dc):
                work[_W_AK + k, i] = g * wp[mi, h + _R_W1T + k, i]
    for i in range(h):
        work[_W_P, i] = wp[mi, h + _R_B2, i]
    if jac:
        for k in range(dc):
            for i in range(h):
                work[_W_BK + k, i] = 0.0
    for m in range(h):
        a = work[_W_H1, m]
        for i in range(h):
            work[_W_P, i] += wp[mi, m, i] * a
        if jac:
            for k in range(dc):
                ak = work[_W_AK + k, m]
                for i in range(h):
                    work[_W_BK + k, i] += wp[mi, m, i] * ak
    for i in range(h):
        a, g = _act(work[_W_P, i], code, jac)
        work[_W_H2, i] = a
        work[_W_G2, i] = g
    for j in range(dout):
        acc = wp[mi, h + _R_B3, j]
        for i in range(h):
            acc += wp[mi, h + _R_W3 + j, i] * work[_W_H2, i]
        work[out_row, j] = acc
    if jac:
        for j in range(dout):
            for k in range(dc):
                acc = 0.0
                for i in range(h):
                    acc += wp[mi, h + _R_W3 + j, i] * work[_W_G2, i] * work[_W_BK + k, i]
                work[jout_row, j * dc + k] = acc


@_jit
def _flow(x, wp, layout, code, jac, work):
    """phi(x) into work[_W_Y], and if ``jac`` J = dphi/dx (row-major) into work[_W_J]."""
    dim = x.shape[0]
    h = wp.shape[1] - _PACK_EXTRA_ROWS
    for i in range(dim):
        work[_W_Y, i] = x[i]
    if jac:
        for i in range(dim):
            for j in range(dim):
                work[_W_J, i * dim + j] = 1.0 if i == j else 0.0
    for layer in range(layout.shape[0]):
        dc = layout[layer, 0]
        dt = layout[layer, 1]
        for k in range(dc):
            work[_W_C, k] = work[_W_Y, layout[layer, _L_COND + k]]
        _mlp(wp, 2 * layer, dc, dt, h, code, jac, work, _W_A, _W_JA)
        _mlp(wp, 2 * layer + 1, dc, dt, h, code, jac, work, _W_T, _W_JT)
        for i in range(dt):
            ti = layout[layer, _L_TRANS + i]
            s = math.tanh(work[_W_A, i])
            e = math.exp(s)
            ze = work[_W_Y, ti] * e
            work[_W_Y, ti] = ze + work[_W_T, i]
            if jac:
                # row ti of J <- e J[ti] + sum_k M[i, k] J[cond_k],  M = diag(z e) ds/dc + dt/dc
                coef = ze * (1.0 - s * s)
                for col in range(dim):
                    acc = e * work[_W_J, ti * dim + col]
                    for k in range(dc):
                        mik = coef * work[_W_JA, i * dc + k] + work[_W_JT, i * dc + k]
                        acc += mik * work[_W_J, layout[layer, _L_COND + k] * dim + col]
                    work[_W_J, ti * dim + col] = acc


@_jit
def _all_finite(v) -> bool:
    for i in range(v.shape[0]):
        if not math.isfinite(v[i]):
            return False
    return True


@_jit
def _phi_kernel(x, wp, layout, code, work, out) -> int:
    if not _all_finite(x):
        return _BAD_X
    _flow(x, wp, layout, code, False, work)
    for i in range(x.shape[0]):
        out[i] = work[_W_Y, i]
    return _OK if _all_finite(out) else _BAD_OUT


@_jit
def _phi_jac_kernel(x, wp, layout, code, work, out, out_j) -> int:
    if not _all_finite(x):
        return _BAD_X
    dim = x.shape[0]
    _flow(x, wp, layout, code, True, work)
    ok = True
    for i in range(dim):
        out[i] = work[_W_Y, i]
        ok = ok and math.isfinite(out[i])
        for j in range(dim):
            out_j[i, j] = work[_W_J, i * dim + j]
            ok = ok and math.isfinite(out_j[i, j])
    return _OK if ok else _BAD_OUT


@_jit
def _potential_kernel(x, wp, layout, code, consts, work) -> int:
    """consts = [S (dim*dim), D (dim*dim), phi_ref (dim), e0]; the value goes to work[_W_POT, 0].

    The potential is psi(E), E = 1/2 e^T S e: E itself up to e0, 2 sqrt(e0 E) - e0 beyond (e0 > 0,
    ``FlowEvaluator.set_force_bound``): continuous with its slope, growing like |e| far out."""
    if not _all_finite(x):
        return _BAD_X
    dim = x.shape[0]
    _flow(x, wp, layout, code, False, work)
    pref = 2 * dim * dim
    for i in range(dim):
        work[_W_E, i] = work[_W_Y, i] - consts[pref + i]
    v = 0.0
    for i in range(dim):
        for j in range(dim):
            v += work[_W_E, i] * consts[i * dim + j] * work[_W_E, j]
    v *= 0.5
    e0 = consts[pref + dim]
    if e0 > 0.0 and v > e0:
        v = 2.0 * math.sqrt(e0 * v) - e0
    work[_W_POT, 0] = v
    return _OK if math.isfinite(work[_W_POT, 0]) else _BAD_OUT


@_jit
def _force_kernel(x, xdot, wp, layout, code, consts, work, out) -> int:
    """u = -J^T (psi'(E) S e + D J xdot), e = phi(x) - phi(x_ref); consts and psi as in
    _potential_kernel (psi' = 1 without a bound, else min(1, sqrt(e0 / E)))."""
    if not _all_finite(x):
        return _BAD_X
    if not _all_finite(xdot):
        return _BAD_XDOT
    dim = x.shape[0]
    _flow(x, wp, layout, code, True, work)
    dd = dim * dim
    for i in range(dim):
        work[_W_E, i] = work[_W_Y, i] - consts[2 * dd + i]
        acc = 0.0
        for j in range(dim):
            acc += work[_W_J, i * dim + j] * xdot[j]
        work[_W_V, i] = acc
    scale = 1.0
    e0 = consts[2 * dd + dim]
    if e0 > 0.0:  # the bounded pull: psi'(E) from E = 1/2 e^T S e
        energy = 0.0
        for i in range(dim):
            for j in range(dim):
                energy += work[_W_E, i] * consts[i * dim + j] * work[_W_E, j]
        energy *= 0.5
        if energy > e0:
            scale = math.sqrt(e0 / energy)
    for i in range(dim):
        pull = 0.0
        drag = 0.0
        for j in range(dim):
            pull += consts[i * dim + j] * work[_W_E, j]
            drag += consts[dd + i * dim + j] * work[_W_V, j]
        work[_W_WV, i] = scale * pull + drag
    ok = True
    for i in range(dim):
        acc = 0.0
        for j in range(dim):
            acc += work[_W_J, j * dim + i] * work[_W_WV, j]
        out[i] = -acc
        ok = ok and math.isfinite(out[i])
    return _OK if ok else _BAD_OUT


# ---- python front end ---------------------------------------------------------------------------


class FlowEvaluator:
    """Compiled phi, J, controller force and potential for one set of policy parameters.

    Build it once per parameter set (off the control loop: it packs the weights, computes
    phi(x_ref) and, with ``warmup``, triggers compilation / cache loading). Each method then
    costs one compiled call. Wrong-size or non-finite inputs raise ``ValueError``, as does a
    non-finite result. Not thread-safe (one shared scratch buffer); ``stiffness``, ``damping``,
    ``x_ref`` and ``phi_ref`` are read-only copies (``move_reference`` moves the anchor; build a new
    evaluator for new weights or gains).
    """

    def __init__(
        self,
        params: PolicyParameters | FlowArchitecture,
        weights: np.ndarray | None = None,
        stiffness: np.ndarray | None = None,
        damping: np.ndarray | None = None,
        x_ref: np.ndarray | None = None,
        *,
        warmup: bool = True,
    ) -> None:
        """From ``PolicyParameters``, or from arch + flat weights (+ S, D default I, x_ref default 0)."""
        if not isinstance(params, PolicyParameters):
            d = params.dim
            if weights is None:
                raise ValueError("weights are required when building from an architecture")
            params = PolicyParameters(
                arch=params,
                weights=weights,
                log_std=np.zeros(1),
                stiffness=np.eye(d) if stiffness is None else stiffness,
                damping=np.eye(d) if damping is None else damping,
                x_ref=np.zeros(d) if x_ref is None else x_ref,
            )
        arch = params.arch
        d = arch.dim
        self.arch = arch
        self.version = params.version
        self.dim = d
        self._shape = (d,)
        self._wp, self._layout = pack(arch, params.weights)
        self._code = ACTIVATION_CODES[arch.activation]
        self.stiffness = params.stiffness.copy()
        self.damping = params.damping.copy()
        self.x_ref = params.x_ref.copy()
        self._work = np.zeros(work_shape(arch))
        self._consts = np.zeros(2 * d * d + d + 1)  # the last entry: e0 of the force bound (0: none)
        self.force_bound = 0.0
        self._consts[: d * d] = self.stiffness.reshape(-1)
        self._consts[d * d : 2 * d * d] = self.damping.reshape(-1)
        self.phi_ref = self.phi(self.x_ref)
        self._consts[2 * d * d : 2 * d * d + d] = self.phi_ref
        if warmup:
            self.force(self.x_ref, np.zeros(d))
            self.phi_and_jacobian(self.x_ref)
            self.potential(self.x_ref)

    @classmethod
    def from_params(cls, params: PolicyParameters, *, warmup: bool = True) -> FlowEvaluator:
        """Same as ``FlowEvaluator(params)``."""
        return cls(params, warmup=warmup)

    def _vec(self, v: Any, name: str) -> np.ndarray:
        """``v`` as a contiguous float64 vector of length dim (no copy in the common case)."""
        if v.__class__ is np.ndarray and v.dtype is _F64 and v.shape == self._shape and v.flags.c_contiguous:
            return v
        try:
            arr = np.ascontiguousarray(v, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name}: not a numeric vector ({exc})") from None
        if arr.shape != self._shape:
            raise ValueError(f"{name}: expected shape {self._shape}, got {arr.shape}")
        return arr

    def _out(self, out: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
        if out is None:
            return np.empty(shape)
        if out.__class__ is not np.ndarray or out.dtype is not _F64 or out.shape != shape:
            raise ValueError(f"out: expected a float64 array of shape {shape}")
        if not out.flags.c_contiguous:
            raise ValueError("out: expected a C-contiguous array")
        return out

    def _raise(self, status: int, x: np.ndarray, xdot: np.ndarray | None = None) -> None:
        if status == _BAD_X:
            raise ValueError(f"x: non-finite value(s) {x.tolist()}")
        if status == _BAD_XDOT:
            raise ValueError(f"xdot: non-finite value(s) {None if xdot is None else xdot.tolist()}")
        raise ValueError(f"flow output is non-finite at x={x.tolist()} (weights too large?)")

    def phi(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """phi(x), shape (dim,)."""
        x = self._vec(x, "x")
        out = self._out(out, self._shape)
        status = _phi_kernel(x, self._wp, self._layout, self._code, self._work, out)
        if status:
            self._raise(status, x)
        return out

    def phi_and_jacobian(
        self, x: np.ndarray, out: np.ndarray | None = None, out_jac: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(phi(x) (dim,), J = dphi/dx (dim, dim))."""
        x = self._vec(x, "x")
        out = self._out(out, self._shape)
        out_jac = self._out(out_jac, (self.dim, self.dim))
        status = _phi_jac_kernel(x, self._wp, self._layout, self._code, self._work, out, out_jac)
        if status:
            self._raise(status, x)
        return out, out_jac

    def move_reference(self, x_ref: np.ndarray) -> None:
        """Move the spring's anchor to ``x_ref`` (m, dim values): x_ref and phi(x_ref) change, the flow
        and the gains do not, so the law stays the same stable controller about a new equilibrium
        (teleoperation moves it a little every tick). Uses the shared scratch buffer: call it on the
        thread that calls ``force``. ``ValueError`` for a wrong-size or non-finite ``x_ref``."""
        x = self._vec(x_ref, "x_ref")
        d = self.dim
        phi_ref = self.phi(x)  # raises before anything changes
        self.x_ref[:] = x
        self.phi_ref = phi_ref
        self._consts[2 * d * d : 2 * d * d + d] = phi_ref

    def set_force_bound(self, bound: float) -> None:
        """Bound the potential's pull to ``bound`` N in the latent space (0: no bound, the plain
        quadratic potential). The potential becomes psi(E), E = 1/2 e^T S e, with psi'(E) =
        min(1, sqrt(e0 / E)) and e0 = bound^2 / (2 lambda_max(S)): still a potential (a function of
        E alone), positive definite and radially unbounded, so the stability proof is unchanged; its
        pull |psi'(E) S e| never exceeds ``bound`` (with the identity flow: the TCP force)."""
        bound = float(bound)
        if not (math.isfinite(bound) and bound >= 0.0):
            raise ValueError(f"force bound must be finite and >= 0 N, got {bound}")
        d = self.dim
        lam = float(np.linalg.eigvalsh(0.5 * (self.stiffness + self.stiffness.T)).max())
        self.force_bound = bound
        self._consts[2 * d * d + d] = bound * bound / (2.0 * lam) if bound > 0.0 else 0.0

    def force(self, x: np.ndarray, xdot: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Controller force u = -J^T psi'(E) S (phi(x)-phi(x_ref)) - J^T D J xdot, shape (dim,)
        (psi' = 1 without a force bound)."""
        # the checks of _vec/_out inlined for the common case: this is the 1 kHz call
        shape = self._shape
        if not (
            x.__class__ is np.ndarray
            and x.dtype is _F64
            and x.shape == shape
            and x.flags.c_contiguous
        ):
            x = self._vec(x, "x")
        if not (
            xdot.__class__ is np.ndarray
            and xdot.dtype is _F64
            and xdot.shape == shape
            and xdot.flags.c_contiguous
        ):
            xdot = self._vec(xdot, "xdot")
        out = np.empty(shape) if out is None else self._out(out, shape)
        status = _force_kernel(x, xdot, self._wp, self._layout, self._code, self._consts, self._work, out)
        if status:
            self._raise(status, x, xdot)
        return out

    def potential(self, x: np.ndarray) -> float:
        """Lyapunov potential psi(E), E = 1/2 (phi(x)-phi(x_ref))^T S (phi(x)-phi(x_ref)) (psi(E) = E
        without a force bound)."""
        x = self._vec(x, "x")
        status = _potential_kernel(x, self._wp, self._layout, self._code, self._consts, self._work)
        if status:
            self._raise(status, x)
        return float(self._work[_W_POT, 0])

    def kernel_args(self) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray]:
        """(packed weights, layout, activation code, consts, work) for calling the kernels from numba code.

        For compiled closed loops (tests, batched rollouts): ``force_kernel(x, xdot, *args, out)`` and
        ``potential_kernel(x, *args)``; after a call, J is in ``work[WORK_JACOBIAN, :dim*dim]``
        and the potential in ``work[WORK_POTENTIAL, 0]``.
        """
        return self._wp, self._layout, self._code, self._consts, self._work


# Public names of the compiled kernels and work rows, for numba callers (see kernel_args).
force_kernel = _force_kernel
potential_kernel = _potential_kernel
WORK_JACOBIAN = _W_J
WORK_POTENTIAL = _W_POT

