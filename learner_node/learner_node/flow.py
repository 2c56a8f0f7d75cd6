"""RealNVP flow in torch for learning, with an analytic, batched, differentiable Jacobian.

The architecture and the flat weight layout are defined once in
``nf_core.flow_spec``; this module and the compiled evaluator
(``nf_controller_node.flow_eval``) both follow it. ``phi_and_jacobian`` builds J = dphi/dx
layer by layer with the chain rule (no autograd over x), so PPO can backpropagate through J
to the weights at the cost of one forward pass.

Two implementations of ``phi_and_jacobian`` give the same values and weight gradients (to
rounding): ``phi_and_jacobian_autograd`` is plain torch ops (any dtype, differentiable any
number of times, usable under ``torch.func``); the default float64 path runs the compiled
batched kernels of ``flow_kernels`` inside one ``autograd.Function`` whose backward is the
analytic vector-Jacobian product (differentiable once). That removes the per-op overhead of
hundreds of tiny tensor ops per PPO minibatch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn
from torch.autograd.function import FunctionCtx, once_differentiable

from nf_core.flow_spec import ACTIVATION_CODES, FLOW_INITS, FlowArchitecture

from .flow_kernels import flow_backward, flow_forward, layer_table

_SQRT_HALF = math.sqrt(0.5)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def activation_and_derivative(
    name: str, p: torch.Tensor, with_derivative: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Activation ``name`` at ``p`` and, if ``with_derivative``, its derivative (both differentiable).

    softplus is the exact log(1 + e^p) (torch.nn.functional.softplus switches to p above 20,
    an error of up to 2e-9); the compiled evaluator uses the same exact form.
    """
    if name == "gelu":
        cdf = 0.5 * (1.0 + torch.erf(p * _SQRT_HALF))
        act = p * cdf  # exact (erf) GELU, torch's default
        der = cdf + p * _INV_SQRT_2PI * torch.exp(-0.5 * p * p) if with_derivative else None
    elif name == "tanh":
        act = torch.tanh(p)
        der = 1.0 - act * act if with_derivative else None
    elif name == "softplus":
        act = torch.logaddexp(p, torch.zeros_like(p))  # log(1 + e^p), exact (no threshold)
        der = torch.sigmoid(p) if with_derivative else None
    else:  # pragma: no cover - FlowArchitecture validates the name
        raise ValueError(f"unknown activation {name!r}")
    return act, der


_MLP_ARRAYS = 6  # W1, b1, W2, b2, W3, b3 of one s or t network (flow_spec order)


def init_flow_weights(
    arch: FlowArchitecture, rng: np.random.Generator, scale: float = 1.0, init: str = "random"
) -> np.ndarray:
    """Flat weight vector in flow_spec order.

    Every weight and bias is uniform in ``±scale/sqrt(fan_in)`` (torch.nn.Linear's default for
    ``scale=1``); ``scale > 1`` gives large weights for stress tests. ``init="identity"`` then
    zeroes the output layer (W3, b3) of every s and t network, so s = t = 0 and phi is the
    identity: the untrained controller is the plain impedance law with S and D, the same for
    every seed. The hidden layers stay random, so gradients reach them once W3 moves.
    """
    if init not in FLOW_INITS:
        raise ValueError(f"flow init must be one of {FLOW_INITS}, got {init!r}")
    out = []
    shapes = arch.param_shapes()
    for i, shape in enumerate(shapes):
        # biases take the fan-in of the weight matrix just before them
        fan_in = shape[1] if len(shape) == 2 else shapes[i - 1][1]
        bound = scale / math.sqrt(fan_in)
        values = rng.uniform(-bound, bound, size=int(np.prod(shape)))
        if init == "identity" and i % _MLP_ARRAYS >= _MLP_ARRAYS - 2:
            values[:] = 0.0
        out.append(values)
    return np.concatenate(out).astype(np.float64)


def output_layer_mask(arch: FlowArchitecture) -> np.ndarray:
    """Boolean mask over the flat weights (flow_spec order): True on the output layers (W3, b3) of every
    s and t network, the entries that are zero in the identity initialisation."""
    parts = []
    for i, shape in enumerate(arch.param_shapes()):
        parts.append(np.full(int(np.prod(shape)), i % _MLP_ARRAYS >= _MLP_ARRAYS - 2))
    return np.concatenate(parts)


def move_flow_to_goal(arch: FlowArchitecture, weights: np.ndarray, x_ref_from: np.ndarray,
                      x_ref_to: np.ndarray, scale: float) -> np.ndarray:
    """Physical flow weights learned around ``x_ref_from`` with ``flow_input_scale`` = ``scale``, moved
    to ``x_ref_to``: the normalised weights (what the nets see, ``(x - x_ref) / scale``) are kept, so the
    landscape sits around the new goal as it did around the old. ``scale`` 0: unchanged (the nets see
    x in metres, nothing is relative to the goal)."""
    if scale <= 0.0:
        return np.asarray(weights, dtype=np.float64).copy()
    normalised = rescale_flow_weights(arch, weights, x_ref_from, scale, inverse=True)
    return rescale_flow_weights(arch, normalised, x_ref_to, scale)


def rescale_flow_weights(
    arch: FlowArchitecture, weights: np.ndarray, x_ref: np.ndarray, scale: float, inverse: bool = False
) -> np.ndarray:
    """Physical flow weights from normalised ones (``inverse``: the other way); a linear map.

    Normalised weights describe coupling nets that see ``(c - x_ref_c) / scale`` (c their conditioning
    coordinates, m) and translate by ``scale`` times their t-output: the same RealNVP bijection with
    ``W1 / scale``, ``b1 - W1 x_ref_c / scale`` and the t-net's ``W3, b3`` times ``scale``. Around a goal
    in metres a coupling net with O(1) weights is otherwise nearly affine over the few centimetres
    that matter (its input barely changes there), so the flow can do little more than S already does.
    Any normalised weights give a valid flow, so stability holds for every draw.
    """
    if scale <= 0.0:
        raise ValueError(f"flow input scale must be > 0, got {scale}")
    w = np.asarray(weights, dtype=np.float64).reshape(-1).copy()
    xr = np.asarray(x_ref, dtype=np.float64).reshape(-1)
    shapes = arch.param_shapes()
    sizes = [int(np.prod(shape)) for shape in shapes]
    offsets = np.cumsum([0, *sizes[:-1]])
    for i, shape in enumerate(shapes):
        layer, k = divmod(i, 2 * _MLP_ARRAYS)
        net, j = divmod(k, _MLP_ARRAYS)
        off, size = int(offsets[i]), sizes[i]
        if j == 0:  # W1 and, next, b1
            cond = list(arch.partition(layer)[0])
            w1 = w[off : off + size].reshape(shape)
            b_off = int(offsets[i + 1])
            if inverse:  # b1_n = b1_p + W1_p x_ref_c, W1_n = scale W1_p
                w[b_off : b_off + shape[0]] += w1 @ xr[cond]
                w[off : off + size] *= scale
            else:  # b1_p = b1_n - W1_n x_ref_c / scale, W1_p = W1_n / scale
                w[off : off + size] /= scale
                w[b_off : b_off + shape[0]] -= w[off : off + size].reshape(shape) @ xr[cond]
        elif net == 1 and j >= _MLP_ARRAYS - 2:  # the t-net's output layer: translations in units of scale
            w[off : off + size] *= (1.0 / scale) if inverse else scale
    return w


class _CompiledPhiJacobian(torch.autograd.Function):
    """(phi, J) of a float64 ``RealNVPFlow`` by the compiled kernels; backward is their analytic VJP."""

    @staticmethod
    def forward(
        ctx: FunctionCtx, flow: RealNVPFlow, keep: bool, x: torch.Tensor, *params: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        w = flow.kernel_weights(params)
        phi, jac, saved = flow_forward(x.detach().contiguous().numpy(), w, flow.table, flow.arch.n_hidden,
                                       flow.activation_code, keep)
        if keep:  # w and saved are private copies: later in-place weight updates cannot touch them
            ctx.flow, ctx.w, ctx.saved = flow, w, saved
        return torch.from_numpy(phi), torch.from_numpy(jac)

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, phi_bar: torch.Tensor, jac_bar: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        flow = ctx.flow
        gw, x_bar = flow_backward(ctx.w, flow.table, flow.arch.n_hidden, ctx.saved,
                                  phi_bar.contiguous().numpy(), jac_bar.contiguous().numpy())
        return (None, None, torch.from_numpy(x_bar) if ctx.needs_input_grad[2] else None,
                *flow.split_flat_gradient(gw))


class RealNVPFlow(nn.Module):
    """The flow phi of flow_spec as a torch module; parameters are kept in flat-vector order.

    The parameter arrays are views into one flat float64 buffer (flow_spec order), so the compiled
    path reads all weights without gathering them; if that aliasing is ever broken (say a
    parameter's ``.data`` is replaced), it gathers them instead.
    """

    def __init__(
        self,
        arch: FlowArchitecture,
        weights: np.ndarray | None = None,
        seed: int = 0,
        dtype: torch.dtype = torch.float64,
        init: str = "random",
    ) -> None:
        """Build the flow; ``weights`` (flat, flow_spec order) default to ``init_flow_weights(seed, init)``."""
        super().__init__()
        self.arch = arch
        self.dtype = dtype
        shapes = arch.param_shapes()
        sizes = [math.prod(shape) for shape in shapes]
        offsets = np.cumsum([0, *sizes[:-1]]).tolist()
        self._flat = torch.zeros(arch.n_params, dtype=dtype)
        self.params = nn.ParameterList(
            [nn.Parameter(v.view(shape)) for v, shape in zip(self._flat.split(sizes), shapes, strict=True)]
        )
        self._layout = list(zip(offsets, sizes, shapes, strict=True))  # per array: flat offset, size, shape
        self._byte_offsets = [off * self._flat.element_size() for off in offsets]
        self._parts: list[tuple[list[int], list[int], list[int]]] = []
        for layer in range(arch.n_layers):
            cond, trans = arch.partition(layer)
            order = list(cond) + list(trans)
            inv = [order.index(i) for i in range(arch.dim)]
            self._parts.append((list(cond), list(trans), inv))
        if weights is None:
            weights = init_flow_weights(arch, np.random.default_rng(seed), init=init)
        self.load_flat(weights)
        self.table = layer_table(arch)  # for the compiled kernels
        self.activation_code = ACTIVATION_CODES[arch.activation]

    # ---- flat parameter vector -------------------------------------------------------------
    def to_flat(self) -> np.ndarray:
        """The weights as a flat float64 numpy vector in flow_spec order."""
        with torch.no_grad():
            return torch.cat([p.reshape(-1) for p in self.params]).to(torch.float64).cpu().numpy().copy()

    def load_flat(self, vec: np.ndarray) -> None:
        """Overwrite the weights from a flat vector in flow_spec order."""
        flat = np.asarray(vec, dtype=np.float64).reshape(-1)
        if flat.size != self.arch.n_params:
            raise ValueError(f"weights: expected {self.arch.n_params} values, got {flat.size}")
        if not np.isfinite(flat).all():
            raise ValueError("weights: non-finite values")
        src = torch.from_numpy(flat)
        pos = 0
        with torch.no_grad():
            for p in self.params:
                n = p.numel()
                p.copy_(src[pos : pos + n].reshape(p.shape).to(p.dtype))
                pos += n

    def compiled(self) -> bool:
        """True if ``phi_and_jacobian`` (and the policy's mean force) use the compiled kernels (float64)."""
        return self.dtype == torch.float64

    def param_list(self) -> list[nn.Parameter]:
        """The parameter arrays in flow_spec order: ``list(self.params)``, read from the ParameterList's
        own dict (iterating the list looks every item up by name, ~20x slower; this is per minibatch)."""
        return list(self.params._parameters.values())

    def kernel_weights(self, params: Sequence[torch.Tensor]) -> np.ndarray:
        """A private float64 copy of ``params`` (this flow's parameters, in order) as the flat vector."""
        base = self._flat.data_ptr()
        if self._flat.dtype == torch.float64 and all(
            p.data_ptr() == base + off for p, off in zip(params, self._byte_offsets, strict=True)
        ):
            return self._flat.numpy().copy()  # the parameters still live in the flat buffer
        return torch.cat([p.detach().reshape(-1) for p in params]).to(torch.float64).numpy()

    def split_flat_gradient(self, grad: np.ndarray) -> list[torch.Tensor]:
        """A flat float64 weight gradient (flow_spec order) as one tensor per parameter array (views)."""
        return [torch.from_numpy(grad[off : off + size].reshape(shape)) for off, size, shape in self._layout]

    # ---- building blocks -------------------------------------------------------------------
    def _mlp(
        self, layer: int, which: int, c: torch.Tensor, need_jac: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Output (N, d_out) of MLP ``which`` (0: s, 1: t) of ``layer`` and its Jacobian (N, d_out, d_in)."""
        base = 12 * layer + 6 * which
        W1, b1, W2, b2, W3, b3 = (self.params[base + k] for k in range(6))
        act = self.arch.activation
        h1, g1 = activation_and_derivative(act, c @ W1.T + b1, need_jac)
        h2, g2 = activation_and_derivative(act, h1 @ W2.T + b2, need_jac)
        out = h2 @ W3.T + b3
        if not need_jac:
            return out, None
        A = g1.unsqueeze(-1) * W1  # (N, h, d_in)
        B = g2.unsqueeze(-1) * torch.matmul(W2, A)  # (N, h, d_in)
        return out, torch.matmul(W3, B)  # (N, d_out, d_in)

    def _layer(
        self, layer: int, x: torch.Tensor, J: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Apply coupling layer ``layer`` to x (N, dim) and, if given, left-multiply J by its Jacobian."""
        cond, trans, inv = self._parts[layer]
        c, z = x[:, cond], x[:, trans]
        need = J is not None
        a, Ja = self._mlp(layer, 0, c, need)
        t, Jt = self._mlp(layer, 1, c, need)
        s = torch.tanh(a)
        e = torch.exp(s)
        ze = z * e
        y = torch.cat([c, ze + t], dim=1)[:, inv]
        if J is None:
            return y, None
        # d y_t / d c = diag(z e) ds/dc + dt/dc,  d y_t / d z = diag(e)
        M = (ze * (1.0 - s * s)).unsqueeze(-1) * Ja + Jt  # (N, d_t, d_c)
        Jc = J[:, cond, :]
        Jtr = e.unsqueeze(-1) * J[:, trans, :] + torch.matmul(M, Jc)
        return y, torch.cat([Jc, Jtr], dim=1)[:, inv, :]

    def _inverse_layer(self, layer: int, y: torch.Tensor) -> torch.Tensor:
        cond, trans, inv = self._parts[layer]
        c, yt = y[:, cond], y[:, trans]
        a, _ = self._mlp(layer, 0, c, False)
        t, _ = self._mlp(layer, 1, c, False)
        z = (yt - t) * torch.exp(-torch.tanh(a))
        return torch.cat([c, z], dim=1)[:, inv]

    def _as_batch(self, x: torch.Tensor | np.ndarray) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=self.dtype)
        if x.dim() != 2 or x.shape[1] != self.arch.dim:
            raise ValueError(f"expected a batch of shape (N, {self.arch.dim}), got {tuple(x.shape)}")
        return x

    # ---- public API ------------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """phi(x) for a batch x of shape (N, dim)."""
        y = self._as_batch(x)
        for layer in range(self.arch.n_layers):
            y, _ = self._layer(layer, y, None)
        return y

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """phi^{-1}(y) for a batch y of shape (N, dim)."""
        x = self._as_batch(y)
        for layer in reversed(range(self.arch.n_layers)):
            x = self._inverse_layer(layer, x)
        return x

    def phi_and_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """phi(x) (N, dim) and J = dphi/dx (N, dim, dim), analytic and differentiable in the weights.

        float64 flows use the compiled kernels (differentiable once, in the weights and x);
        other dtypes use ``phi_and_jacobian_autograd``.
        """
        if not self.compiled():
            return self.phi_and_jacobian_autograd(x)
        x = self._as_batch(x)
        params = self.param_list()
        keep = torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in params))
        return _CompiledPhiJacobian.apply(self, keep, x, *params)

    def phi_and_jacobian_autograd(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Same as ``phi_and_jacobian`` in plain torch ops (the reference; any order of derivatives)."""
        y = self._as_batch(x)
        J = torch.eye(self.arch.dim, dtype=y.dtype, device=y.device).expand(y.shape[0], -1, -1)
        for layer in range(self.arch.n_layers):
            y, J = self._layer(layer, y, J)
        return y, J
