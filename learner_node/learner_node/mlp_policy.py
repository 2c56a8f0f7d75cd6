"""Plain Gaussian MLP policy (the PPO baseline of the paper) and its compiled evaluator.

Same interface as ``NFPolicy``: the mean action is a task-space force

    u = MLP([x - x_ref, xdot])

(two hidden layers, linear output, N), plus Gaussian noise with one trainable log-std shared by
all action dimensions. Only the parameterisation differs from NF-PPO: there is no stability
guarantee and no potential. ``MLPEvaluator`` evaluates the same function in float64 with numba,
with the ``force(x, xdot, out)`` / ``potential(x)`` interface ``FlowController`` expects.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import numba
import numpy as np
import torch
from torch import nn

from .gaussian import GaussianForceMixin

ACTIVATION_CODES = {"tanh": 0, "gelu": 1}
OUTPUT_SCALE = 0.01  # the output layer starts this much smaller than torch's default: u ~ 0 at first
_SQRT_HALF = math.sqrt(0.5)


class MLPPolicy(GaussianForceMixin, nn.Module):
    """Gaussian MLP policy over task-space forces: mean MLP([x - x_ref, xdot]), trainable shared log-std."""

    def __init__(
        self,
        dim: int,
        n_hidden: int = 64,
        activation: str = "tanh",
        x_ref: np.ndarray | None = None,
        sigma_init: float = 1.0,
        log_std: np.ndarray | None = None,
        seed: int = 0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        """Weights uniform in +-1/sqrt(fan_in) from ``seed`` (torch's default bound), the output layer
        scaled by ``OUTPUT_SCALE``; log_std defaults to ``[log(sigma_init)]``."""
        super().__init__()
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        if activation not in ACTIVATION_CODES:
            raise ValueError(f"activation must be one of {tuple(ACTIVATION_CODES)}, got {activation!r}")
        if n_hidden < 1:
            raise ValueError(f"n_hidden must be >= 1, got {n_hidden}")
        self.dim = dim
        self.n_hidden = n_hidden
        self.activation = activation
        self.dtype = dtype
        self.layers = nn.ModuleList(
            [nn.Linear(2 * dim, n_hidden, dtype=dtype), nn.Linear(n_hidden, n_hidden, dtype=dtype),
             nn.Linear(n_hidden, dim, dtype=dtype)]
        )
        rng = np.random.default_rng(seed)
        with torch.no_grad():
            for i, layer in enumerate(self.layers):
                bound = 1.0 / math.sqrt(layer.in_features) * (OUTPUT_SCALE if i == 2 else 1.0)
                layer.weight.copy_(torch.from_numpy(rng.uniform(-bound, bound, tuple(layer.weight.shape))))
                layer.bias.copy_(torch.from_numpy(rng.uniform(-bound, bound, tuple(layer.bias.shape))))
        ref = np.zeros(dim) if x_ref is None else np.asarray(x_ref, dtype=np.float64).reshape(dim)
        self.register_buffer("x_ref", torch.as_tensor(ref, dtype=dtype).clone())
        if log_std is None:
            if not sigma_init > 0:
                raise ValueError(f"sigma_init must be > 0, got {sigma_init}")
            log_std = np.array([math.log(sigma_init)])
        ls = np.asarray(log_std, dtype=np.float64).reshape(-1)
        if ls.size not in (1, dim):
            raise ValueError(f"log_std: expected 1 or {dim} values, got {ls.size}")
        self.log_std = nn.Parameter(torch.as_tensor(ls, dtype=dtype).clone())

    def _act(self, p: torch.Tensor) -> torch.Tensor:
        if self.activation == "tanh":
            return torch.tanh(p)
        return p * 0.5 * (1.0 + torch.erf(p * _SQRT_HALF))  # exact GELU, as the evaluator

    def mean_force(self, x: torch.Tensor, xdot: torch.Tensor) -> torch.Tensor:
        """Mean force for batches x, xdot of shape (N, dim) (or (dim,)); returns (N, dim) (or (dim,))."""
        x = torch.as_tensor(x, dtype=self.dtype)
        xdot = torch.as_tensor(xdot, dtype=self.dtype)
        h = torch.cat([x - self.x_ref, xdot], dim=-1)
        h = self._act(self.layers[0](h))
        h = self._act(self.layers[1](h))
        return self.layers[2](h)

    def weights(self) -> list[np.ndarray]:
        """[W1, b1, W2, b2, W3, b3] as float64 numpy copies (W is (out, in))."""
        out = []
        with torch.no_grad():
            for layer in self.layers:
                out.append(layer.weight.to(torch.float64).cpu().numpy().copy())
                out.append(layer.bias.to(torch.float64).cpu().numpy().copy())
        return out


# ---- compiled evaluator -----------------------------------------------------------------------------


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True)``, without caching when no cache directory is writable."""
    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError as exc:
        warnings.warn(f"numba caching disabled for {fn.__name__}: {exc}", RuntimeWarning, stacklevel=2)
        return numba.njit(cache=False)(fn)


@_jit
def _act(p: float, code: int) -> float:
    if code == 0:
        return math.tanh(p)
    return p * 0.5 * (1.0 + math.erf(p * _SQRT_HALF))


@_jit
def _mlp_force_kernel(x, xdot, x_ref, W1, b1, W2, b2, W3, b3, code, h1, h2, out) -> bool:
    """out = MLP([x - x_ref, xdot]); False if an input or the output is not finite."""
    d = x.shape[0]
    for k in range(d):
        if not (math.isfinite(x[k]) and math.isfinite(xdot[k])):
            return False
    h = b1.shape[0]
    for i in range(h):
        acc = b1[i]
        for k in range(d):
            acc += W1[i, k] * (x[k] - x_ref[k]) + W1[i, d + k] * xdot[k]
        h1[i] = _act(acc, code)
    for i in range(h):
        acc = b2[i]
        for m in range(h):
            acc += W2[i, m] * h1[m]
        h2[i] = _act(acc, code)
    ok = True
    for j in range(d):
        acc = b3[j]
        for m in range(h):
            acc += W3[j, m] * h2[m]
        out[j] = acc
        ok = ok and math.isfinite(acc)
    return ok


class MLPEvaluator:
    """Compiled float64 mean force of an ``MLPPolicy`` for the 1 kHz loop (``FlowController`` compatible).

    Not thread-safe (shared scratch buffers). Non-finite input or output raises ``ValueError``.
    """

    def __init__(self, weights: list[np.ndarray], x_ref: np.ndarray, activation: str = "tanh") -> None:
        """From [W1, b1, W2, b2, W3, b3] (W as (out, in)), the goal and the hidden activation."""
        if activation not in ACTIVATION_CODES:
            raise ValueError(f"activation must be one of {tuple(ACTIVATION_CODES)}, got {activation!r}")
        if len(weights) != 6:
            raise ValueError(f"expected 6 weight arrays [W1, b1, W2, b2, W3, b3], got {len(weights)}")
        self._w = [np.ascontiguousarray(w, dtype=np.float64) for w in weights]
        self.x_ref = np.ascontiguousarray(x_ref, dtype=np.float64).reshape(-1)
        self.dim = self.x_ref.shape[0]
        W1, b1, W2, b2, W3, b3 = self._w
        h = b1.shape[0]
        d = self.dim
        shapes_ok = (W1.shape == (h, 2 * d) and W2.shape == (h, h) and b2.shape == (h,)
                     and W3.shape == (d, h) and b3.shape == (d,))
        if not shapes_ok:
            raise ValueError(f"inconsistent MLP weight shapes {[w.shape for w in self._w]} for dim {d}")
        if not all(np.all(np.isfinite(w)) for w in self._w):
            raise ValueError("MLP weights contain NaN or Inf")
        self._code = ACTIVATION_CODES[activation]
        self._h1 = np.zeros(h)
        self._h2 = np.zeros(h)
        self.force(self.x_ref, np.zeros(d))  # compile / load from cache now, not in the loop

    @classmethod
    def from_policy(cls, policy: MLPPolicy) -> MLPEvaluator:
        """Snapshot of ``policy``'s current mean."""
        return cls(policy.weights(), policy.x_ref.detach().cpu().numpy(), policy.activation)

    def force(self, x: np.ndarray, xdot: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Mean force u = MLP([x - x_ref, xdot]), shape (dim,), written to ``out`` if given."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        xdot = np.ascontiguousarray(xdot, dtype=np.float64)
        if x.shape != (self.dim,) or xdot.shape != (self.dim,):
            raise ValueError(f"x, xdot: expected shape ({self.dim},), got {x.shape}, {xdot.shape}")
        if out is None:
            out = np.empty(self.dim)
        elif out.dtype != np.float64 or out.shape != (self.dim,) or not out.flags.c_contiguous:
            raise ValueError(f"out: expected a C-contiguous float64 array of shape ({self.dim},)")
        if not _mlp_force_kernel(x, xdot, self.x_ref, *self._w, self._code, self._h1, self._h2, out):
            raise ValueError(f"MLP force is not finite at x={x.tolist()}, xdot={xdot.tolist()}")
        return out

    def potential(self, x: np.ndarray) -> float:
        """NaN: a plain MLP policy defines no potential (no Lyapunov function, no stability guarantee)."""
        return float("nan")
