"""Stochastic normalizing-flow policy for PPO: the stable controller law plus Gaussian noise.

Mean action (the deterministic, provably stable controller)::

    u = -J(x)^T S [phi(x) - phi(x_ref)] - J(x)^T D J(x) xdot

with trainable flow weights and a trainable log-std; x_ref is fixed. S and D are fixed, or (``gains=
"learned"``) diagonal with trainable log-entries, S = diag(exp(ln_s)), D = diag(exp(ln_d)): every
value is symmetric positive definite, so the stability proof holds for every step of learning.

For a float64 policy the mean force (flow, phi(x_ref) in the same batched pass, and the
controller law) is one compiled call per batch, with the analytic vector-Jacobian product as its
backward (``flow_kernels``); ``mean_force_reference`` is the same function in plain torch ops.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.autograd.function import FunctionCtx, once_differentiable

from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import POLICY_LIMITS, PolicyLaw, PolicyParameters

from .flow import RealNVPFlow
from .flow_kernels import force_backward, force_forward
from .gaussian import GaussianForceMixin

# learned gains stay within what the controller accepts (clamped in log space)
LN_MAX_STIFFNESS = math.log(POLICY_LIMITS.max_stiffness)
LN_MAX_DAMPING = math.log(POLICY_LIMITS.max_damping)


def _matrix(values: np.ndarray | torch.Tensor | None, dim: int, dtype: torch.dtype) -> torch.Tensor:
    if values is None:
        return torch.eye(dim, dtype=dtype)
    return torch.as_tensor(np.asarray(values, dtype=np.float64).reshape(dim, dim), dtype=dtype).clone()


class _CompiledMeanForce(torch.autograd.Function):
    """``NFPolicy.mean_force`` by the compiled kernels; backward (to x and the flow weights) is their VJP."""

    @staticmethod
    def forward(
        ctx: FunctionCtx, policy: NFPolicy, keep: bool, x: torch.Tensor, xdot: torch.Tensor, S_t: torch.Tensor,
        D_t: torch.Tensor, *params: torch.Tensor
    ) -> torch.Tensor:
        flow = policy.flow
        w = flow.kernel_weights(params)
        S, D = S_t.detach().numpy(), D_t.detach().numpy()
        u, jac, wv, saved = force_forward(
            x.detach().contiguous().numpy(), xdot.detach().contiguous().numpy(), policy.x_ref.numpy(), S, D,
            w, flow.table, flow.arch.n_hidden, flow.activation_code, keep,
        )
        if keep:  # private copies, safe from in-place updates (xdot: version-checked by autograd)
            ctx.save_for_backward(xdot)
            ctx.flow, ctx.w, ctx.S, ctx.D, ctx.jac, ctx.wv, ctx.saved = flow, w, S.copy(), D.copy(), jac, wv, saved
        return torch.from_numpy(u)

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, u_bar: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        (xdot,) = ctx.saved_tensors
        flow = ctx.flow
        ub, xd = u_bar.contiguous().numpy(), xdot.detach().contiguous().numpy()
        gw, x_bar = force_backward(ub, xd, ctx.S, ctx.D, ctx.jac, ctx.wv, ctx.w, flow.table, flow.arch.n_hidden,
                                   ctx.saved)
        gS = gD = None
        if ctx.needs_input_grad[4] or ctx.needs_input_grad[5]:
            # u = -J^T w, w = S e + D v (v = J xdot): dL/dS = w_bar e^T, dL/dD = w_bar v^T, w_bar = -J u_bar
            n = ub.shape[0]
            jac = ctx.jac[:n]
            w_bar = -np.einsum("sij,sj->si", jac, ub)
            v = np.einsum("sij,sj->si", jac, xd)
            e = np.linalg.solve(ctx.S, (ctx.wv - v @ ctx.D.T).T).T
            gS = torch.from_numpy(w_bar.T @ e) if ctx.needs_input_grad[4] else None
            gD = torch.from_numpy(w_bar.T @ v) if ctx.needs_input_grad[5] else None
        return (None, None, torch.from_numpy(x_bar) if ctx.needs_input_grad[2] else None, None, gS, gD,
                *flow.split_flat_gradient(gw))


class NFPolicy(GaussianForceMixin, nn.Module):
    """Flow controller policy: trainable flow and log-std, SPD S and D (fixed, or learned diagonals),
    fixed goal x_ref."""

    def __init__(
        self,
        arch: FlowArchitecture,
        weights: np.ndarray | None = None,
        stiffness: np.ndarray | None = None,
        damping: np.ndarray | None = None,
        x_ref: np.ndarray | None = None,
        sigma_init: float = 1.0,
        log_std: np.ndarray | None = None,
        seed: int = 0,
        dtype: torch.dtype = torch.float64,
        flow_init: str = "random",
        learn_gains: bool = False,
        stiffness_floor: float = 0.0,
        law: PolicyLaw | None = None,
    ) -> None:
        """S, D default to identity, x_ref to zero; log_std defaults to ``[log(sigma_init)]`` (shared);
        without ``weights`` the flow starts from ``init_flow_weights(seed, flow_init)``. ``learn_gains``:
        S and D must be diagonal; their log-diagonals become the parameters ``ln_s`` and ``ln_d``.
        ``stiffness_floor`` (N/m, learned gains only; 0: none): no diagonal entry of S goes below it.
        ``law``: the law the policy runs under (``to_params`` carries it; default ``PolicyLaw`` with the floor)."""
        super().__init__()
        d = arch.dim
        self.arch = arch
        self.dtype = dtype
        self.flow = RealNVPFlow(arch, weights, seed=seed, dtype=dtype, init=flow_init)
        self.register_buffer("S", _matrix(stiffness, d, dtype))
        self.register_buffer("D", _matrix(damping, d, dtype))
        ref = np.zeros(d) if x_ref is None else np.asarray(x_ref, dtype=np.float64).reshape(d)
        self.register_buffer("x_ref", torch.as_tensor(ref, dtype=dtype).clone())
        if log_std is None:
            if sigma_init <= 0:
                raise ValueError(f"sigma_init must be > 0, got {sigma_init}")
            log_std = np.array([math.log(sigma_init)])
        ls = np.asarray(log_std, dtype=np.float64).reshape(-1)
        if ls.size not in (1, d):
            raise ValueError(f"log_std: expected 1 or {d} values, got {ls.size}")
        self.log_std = nn.Parameter(torch.as_tensor(ls, dtype=dtype).clone())
        self.learn_gains = bool(learn_gains)
        if self.learn_gains:
            for name in ("S", "D"):
                m = getattr(self, name)
                if not torch.equal(m, torch.diag(torch.diagonal(m))) or not bool((torch.diagonal(m) > 0).all()):
                    raise ValueError(f"learned gains need a positive diagonal {name}, got {m.tolist()}")
            self.ln_s = nn.Parameter(torch.log(torch.diagonal(self.S)).clone())
            self.ln_d = nn.Parameter(torch.log(torch.diagonal(self.D)).clone())
        if stiffness_floor < 0.0 or (stiffness_floor > 0.0 and not self.learn_gains):
            raise ValueError(f"stiffness_floor must be >= 0 and needs learned gains, got {stiffness_floor}")
        # ln of the floor (None: none), and whether S started below it (a wrong prior, refused)
        self.ln_s_floor = math.log(stiffness_floor) if stiffness_floor > 0.0 else None
        if self.ln_s_floor is not None and bool((self.ln_s < self.ln_s_floor).any()):
            raise ValueError(f"S {torch.diagonal(self.S).tolist()} starts below stiffness_floor {stiffness_floor}")
        if law is not None and stiffness_floor > 0.0 and law.stiffness_floor != stiffness_floor:
            raise ValueError(f"stiffness_floor {stiffness_floor} differs from the law's {law.stiffness_floor}")
        self.law = law if law is not None else PolicyLaw(stiffness_floor=stiffness_floor)

    # ---- gains -------------------------------------------------------------------------------
    def gains(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, D) as used by the controller now: the fixed buffers, or diag(exp(ln_s)), diag(exp(ln_d))
        (differentiable in ln_s, ln_d)."""
        if self.learn_gains:
            return torch.diag(torch.exp(self.ln_s.clamp(min=self.ln_s_floor, max=LN_MAX_STIFFNESS))), torch.diag(
                torch.exp(self.ln_d.clamp(max=LN_MAX_DAMPING)))
        return self.S, self.D

    def raise_to_floor(self) -> list[int]:
        """Lift every learned ln S entry below ``stiffness_floor`` onto it (a loaded policy's); returns the
        indices lifted."""
        if self.ln_s_floor is None:
            return []
        with torch.no_grad():
            low = (self.ln_s < self.ln_s_floor).nonzero().reshape(-1).tolist()
            self.ln_s.clamp_(min=self.ln_s_floor)
        self.sync_gains()
        return low

    def sync_gains(self) -> None:
        """Copy the learned gains into the buffers ``S`` and ``D`` (no-op for fixed gains)."""
        if self.learn_gains:
            with torch.no_grad():
                S, D = self.gains()
                self.S.copy_(S)
                self.D.copy_(D)

    # ---- controller --------------------------------------------------------------------------
    def _batch(self, v: torch.Tensor | np.ndarray) -> torch.Tensor:
        v = torch.as_tensor(v, dtype=self.dtype)
        return v.unsqueeze(0) if v.dim() == 1 else v

    def phi_ref(self) -> torch.Tensor:
        """phi(x_ref), shape (dim,)."""
        return self.flow(self.x_ref.unsqueeze(0))[0]

    def mean_force(self, x: torch.Tensor, xdot: torch.Tensor) -> torch.Tensor:
        """Deterministic controller u for batches x, xdot of shape (N, dim) (or (dim,)); returns (N, dim)."""
        squeeze = torch.as_tensor(x).dim() == 1
        x, xdot = self._batch(x), self._batch(xdot)
        S, D = self.gains()
        if self.flow.compiled() and not any(t.requires_grad for t in (xdot, self.x_ref)):
            params = self.flow.param_list()
            keep = torch.is_grad_enabled() and (
                x.requires_grad or S.requires_grad or D.requires_grad or any(p.requires_grad for p in params))
            u = _CompiledMeanForce.apply(self, keep, x, xdot, S, D, *params)
        else:
            u = self.mean_force_reference(x, xdot)
        return u[0] if squeeze else u

    def mean_force_reference(self, x: torch.Tensor, xdot: torch.Tensor) -> torch.Tensor:
        """``mean_force`` for batches (N, dim) in plain torch ops (any dtype, any order of derivatives)."""
        # phi(x_ref) in the same batched pass as the states
        phi_all, J_all = self.flow.phi_and_jacobian_autograd(torch.cat([x, self.x_ref.unsqueeze(0)]))
        n = x.shape[0]
        err = phi_all[:n] - phi_all[n]
        J = J_all[:n]
        # w = S e + D J xdot;  u = -J^T w
        Jv = torch.einsum("nij,nj->ni", J, xdot)
        S, D = self.gains()
        w = err @ S.T + Jv @ D.T
        return -torch.einsum("nji,nj->ni", J, w)

    def lyapunov_potential(self, x: torch.Tensor) -> torch.Tensor:
        """1/2 (phi(x)-phi(x_ref))^T S (phi(x)-phi(x_ref)) for a batch x; shape (N,) (or scalar)."""
        squeeze = torch.as_tensor(x).dim() == 1
        err = self.flow(self._batch(x)) - self.phi_ref()
        v = 0.5 * torch.einsum("ni,ij,nj->n", err, self.gains()[0], err)
        return v[0] if squeeze else v

    # ---- parameters message ------------------------------------------------------------------
    def to_params(self, version: int = 0) -> PolicyParameters:
        """Snapshot as validated ``PolicyParameters`` (what the controller node receives)."""
        with torch.no_grad():
            S, D = self.gains()
            return PolicyParameters(
                arch=self.arch,
                weights=self.flow.to_flat(),
                log_std=self.log_std.detach().to(torch.float64).cpu().numpy().copy(),
                stiffness=S.to(torch.float64).cpu().numpy().copy(),
                damping=D.to(torch.float64).cpu().numpy().copy(),
                x_ref=self.x_ref.to(torch.float64).cpu().numpy().copy(),
                version=int(version),
                law=self.law,
            )

    @classmethod
    def from_params(cls, p: PolicyParameters, dtype: torch.dtype = torch.float64) -> NFPolicy:
        """Rebuild a policy from ``PolicyParameters``."""
        return cls(
            p.arch,
            weights=p.weights,
            stiffness=p.stiffness,
            damping=p.damping,
            x_ref=p.x_ref,
            log_std=p.log_std,
            dtype=dtype,
            law=p.law,
        )
