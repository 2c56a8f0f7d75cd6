"""Exploration in parameter space for the NF policy: every rollout is a deterministic stable controller.

Instead of adding force noise to the controller's output, each rollout of an iteration runs the
deterministic flow controller with its own parameters theta drawn around the policy's
(``theta = mu + sigma * eps``): the log-diagonals of S and D (``gains="learned"``) and, if
``param_sigma_flow > 0``, the flow weights along a few fixed random directions of the s/t output
layers (in normalised units if ``flow_input_scale > 0``, see ``rescale_flow_weights``). Whatever
theta is drawn, S and D stay symmetric positive definite and phi a bijection, so each exploration
rollout is itself a provably stable, passive closed loop; and the exploration is coherent over the
whole trajectory (a force sample held 10 ms barely moves the gear; a softer axis acts for the whole
episode).

Rollouts come in mirrored pairs ``mu +- sigma eps`` from the same start (an odd last rollout runs
``mu`` itself), so a pair's return difference is due to its parameters alone, not to its start:
the advantage of each member is half the difference (Sehnke et al.'s symmetric sampling). The
update (``param_ppo``) is PPO's clipped surrogate over rollouts, with log-probability the Gaussian
density of theta, for the mean (the policy's own parameters) and the per-group log-std.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import nn

from nf_core.policy_params import PolicyParameters

from .flow import output_layer_mask, rescale_flow_weights
from .policy import LN_MAX_DAMPING, LN_MAX_STIFFNESS, NFPolicy

_LOG_2PI = math.log(2.0 * math.pi)


class ParamExploration(nn.Module):
    """Gaussian distribution over the explored parameters of an ``NFPolicy`` (mean = the policy's own)."""

    def __init__(
        self, policy: NFPolicy, sigma_gains: float, sigma_flow: float, flow_scale: float = 0.0,
        flow_dim: int = 8,
        seed: int = 0,
    ) -> None:
        """Explore ln S, ln D (if the policy learns its gains) with std ``sigma_gains`` per entry, and the
        flow along ``flow_dim`` fixed random unit directions in the s/t output layers' weights (drawn from
        ``seed``; a few mirrored pairs can estimate a gradient in a few directions, not in hundreds) with
        one shared std ``sigma_flow`` (if > 0). ``flow_scale`` > 0: the flow is explored and learned in
        normalised weights (nets that see (x - x_ref) / flow_scale, ``rescale_flow_weights``), so one std
        means the same in every weight whatever the units of x."""
        super().__init__()
        self.policy = [policy]  # a list: not a submodule (its parameters belong to the policy)
        dt = policy.dtype
        self.explore_gains = policy.learn_gains
        self.explore_flow = sigma_flow > 0.0
        if not (self.explore_gains or self.explore_flow):
            raise ValueError("nothing to explore: the policy's gains are fixed and sigma_flow is 0")
        d = policy.arch.dim
        n_gain = 2 * d if self.explore_gains else 0
        self.log_sigma_gains = nn.Parameter(torch.full((n_gain,), math.log(sigma_gains), dtype=dt))
        self.log_sigma_flow = nn.Parameter(torch.full((1 if self.explore_flow else 0,),
                                                      math.log(sigma_flow) if self.explore_flow else 0.0, dtype=dt))
        self.n_gain = n_gain
        self.flow_scale = float(flow_scale)
        mask = output_layer_mask(policy.arch)
        self._flow_mask = mask
        # the full flow in the explored coordinates; the mean ``flow_mu`` is the offset along the basis
        base = self._to_explored(policy.flow.to_flat())
        self.register_buffer("flow_base", torch.from_numpy(base))
        basis = np.random.default_rng([seed, 31]).standard_normal((int(mask.sum()), flow_dim))
        basis /= np.linalg.norm(basis, axis=0)
        self.register_buffer("flow_basis", torch.from_numpy(basis))
        mu0 = np.zeros(flow_dim)
        self.flow_mu = nn.Parameter(torch.from_numpy(mu0 if self.explore_flow else mu0[:0].copy()))
        self.n_flow = mu0.size if self.explore_flow else 0
        # running advantage scale: sum and count of the iterations' pair RMS
        self.register_buffer("adv_rms_sum", torch.zeros((), dtype=torch.float64))
        self.register_buffer("adv_rms_count", torch.zeros((), dtype=torch.float64))

    @property
    def dim(self) -> int:
        """Number of explored parameters."""
        return self.n_gain + self.n_flow

    def mean_parameters(self) -> list[nn.Parameter]:
        """The policy parameters that are the distribution's mean (optimised by the update)."""
        pol = self.policy[0]
        out: list[nn.Parameter] = []
        if self.explore_gains:
            out += [pol.ln_s, pol.ln_d]
        if self.explore_flow:
            out.append(self.flow_mu)
        return out

    def mean(self) -> torch.Tensor:
        """mu, flat (dim,), differentiable in the policy's parameters."""
        return torch.cat([p.reshape(-1) for p in self.mean_parameters()])

    def sigma(self) -> torch.Tensor:
        """Per-coordinate std (dim,), differentiable in the log-stds."""
        parts = []
        if self.explore_gains:
            parts.append(torch.exp(self.log_sigma_gains))
        if self.explore_flow:
            parts.append(torch.exp(self.log_sigma_flow).expand(self.n_flow))
        return torch.cat(parts)

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n`` parameter vectors (n, dim) in mirrored pairs (odd n: the last is mu) and their eps."""
        eps = np.zeros((n, self.dim))
        half = rng.standard_normal((n // 2, self.dim))
        eps[0 : 2 * (n // 2) : 2] = half
        eps[1 : 2 * (n // 2) : 2] = -half
        with torch.no_grad():
            mu, sig = self.mean().numpy(), self.sigma().numpy()
        return mu + sig * eps, eps

    def params_for(self, theta: np.ndarray) -> PolicyParameters:
        """The controller parameters of one draw ``theta`` (the policy's, with the explored ones replaced)."""
        base = self.policy[0].to_params()
        d = base.x_ref.shape[0]
        changes: dict[str, np.ndarray] = {}
        if self.explore_gains:
            floor = self.policy[0].ln_s_floor
            changes["stiffness"] = np.diag(np.exp(np.clip(theta[:d], -np.inf if floor is None else floor,
                                                          LN_MAX_STIFFNESS)))
            changes["damping"] = np.diag(np.exp(np.minimum(theta[d : 2 * d], LN_MAX_DAMPING)))
        if self.explore_flow:
            changes["weights"] = self.flow_weights(np.asarray(theta[self.n_gain :], dtype=np.float64))
        return dataclasses.replace(base, **changes)

    def _to_explored(self, weights: np.ndarray) -> np.ndarray:
        """Physical flow weights in the explored coordinates (normalised if ``flow_scale`` > 0)."""
        if self.flow_scale <= 0.0:
            return np.asarray(weights, dtype=np.float64).copy()
        pol = self.policy[0]
        return rescale_flow_weights(pol.arch, weights, pol.x_ref.numpy(), self.flow_scale, inverse=True)

    def flow_weights(self, explored: np.ndarray) -> np.ndarray:
        """Physical flow weights (what the controller receives) of explored-entry values ``explored``."""
        full = self.flow_base.numpy().copy()
        full[self._flow_mask] += self.flow_basis.numpy() @ explored
        if self.flow_scale <= 0.0:
            return full
        pol = self.policy[0]
        return rescale_flow_weights(pol.arch, full, pol.x_ref.numpy(), self.flow_scale)

    def sync_policy(self) -> None:
        """Write the mean into the policy (learned gains into S, D; the flow mean into its weights)."""
        pol = self.policy[0]
        pol.sync_gains()
        if self.explore_flow:
            pol.flow.load_flat(self.flow_weights(self.flow_mu.detach().numpy()))

    def use_basis(self, basis: np.ndarray | torch.Tensor, sigma: float | None = None) -> None:
        """Explore the flow along the columns of ``basis`` (n_params, k) over all its weights (explored
        coordinates), from the policy's flow as it is now (the mean's offset 0), with std ``sigma`` (None:
        as it is). E.g. the demonstrations' directions (``flow_fit.demo_basis``): a unit along a column is
        the change of the fitted flow when a demonstration moves by a set distance. Call
        ``restart_optimizer`` of the update rule afterwards (the mean is a new parameter)."""
        basis = torch.as_tensor(np.asarray(basis, dtype=np.float64))
        n = self.policy[0].arch.n_params
        if basis.ndim != 2 or basis.shape[0] != n or not bool(torch.isfinite(basis).all()):
            raise ValueError(f"a flow basis must be finite, of shape ({n}, k), got {tuple(basis.shape)}")
        self._flow_mask = np.ones(n, dtype=bool)
        self.flow_basis = basis
        self.flow_base = torch.from_numpy(self._to_explored(self.policy[0].flow.to_flat()))
        k = basis.shape[1]
        self.flow_mu = nn.Parameter(torch.zeros(k, dtype=torch.float64))
        self.n_flow = k
        self.explore_flow = True
        if sigma is not None or not self.log_sigma_flow.numel():
            self.log_sigma_flow = nn.Parameter(torch.full((1,), math.log(sigma or 1.0), dtype=torch.float64))

    def load_state_dict(self, state: dict, strict: bool = True, assign: bool = False) -> object:
        """As nn.Module's; a state without the flow entries (written before the flow could be explored
        in its own coordinates, hence gains only) keeps this explorer's own; a state whose basis spans the
        whole flow (``use_basis``) brings it along."""
        state = dict(state)
        basis = state.get("flow_basis")
        if basis is not None and tuple(basis.shape) != tuple(self.flow_basis.shape):
            self.use_basis(basis)
        for key in ("flow_base", "flow_mu", "adv_rms_sum", "adv_rms_count"):
            if key not in state and not (key == "flow_mu" and self.explore_flow):
                state[key] = getattr(self, key).detach().clone()
        return super().load_state_dict(state, strict=strict, assign=assign)

    def running_scale(self, raw: np.ndarray) -> float:
        """Add this iteration's pair RMS of ``raw`` (pair advantages) and return the mean pair RMS over all
        iterations so far, this one included (0: none), to divide the advantages by.

        Normalising each batch to unit size makes an iteration whose pairs differ only by the reward's
        small shaping terms (every rollout inserts) step as far as one where half of them fail: late in
        a gear run that walked the lateral stiffness down by 2x (towards less torque) until rollouts
        stalled on the shaft again. With a running scale such iterations take small steps."""
        rms = pair_rms(raw)
        if rms > 0.0:
            self.adv_rms_sum += rms
            self.adv_rms_count += 1.0
        count = float(self.adv_rms_count)
        return float(self.adv_rms_sum) / count if count else 0.0

    def set_mean(self, theta: np.ndarray) -> None:
        """Move the mean to ``theta`` (dim,), in the explored coordinates (ln S, ln D, flow)."""
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape != (self.dim,) or not np.all(np.isfinite(theta)):
            raise ValueError(f"set_mean needs {self.dim} finite values, got shape {theta.shape}")
        with torch.no_grad():
            start = 0
            for p in self.mean_parameters():
                n = p.numel()
                p.copy_(torch.from_numpy(theta[start : start + n]).reshape(p.shape).to(p.dtype))
                start += n

    def decay(self, factor: float) -> None:
        """Multiply every exploration std by ``factor``."""
        if factor != 1.0:
            with torch.no_grad():
                self.log_sigma_gains.add_(math.log(factor))
                self.log_sigma_flow.add_(math.log(factor))

    def group_log_probs(self, theta: torch.Tensor) -> list[torch.Tensor]:
        """Gaussian log-density of each row of ``theta`` (K, dim) per explored group (gains, flow): the
        distribution factorises, so each is the exact density of that group's part of the draw."""
        mu, sig = self.mean(), self.sigma()
        z = (theta - mu) / sig
        out = []
        for lo, hi in ((0, self.n_gain), (self.n_gain, self.dim)):
            if hi > lo:
                out.append(-0.5 * (z[:, lo:hi] ** 2).sum(dim=1) - torch.log(sig[lo:hi]).sum()
                           - 0.5 * (hi - lo) * _LOG_2PI)
        return out

    def log_prob(self, theta: torch.Tensor) -> torch.Tensor:
        """Gaussian log-density of each row of ``theta`` (K, dim), differentiable in mu and the log-stds."""
        mu, sig = self.mean(), self.sigma()
        z = (theta - mu) / sig
        return -0.5 * (z * z).sum(dim=1) - torch.log(sig).sum() - 0.5 * self.dim * _LOG_2PI


def paired_advantages(returns: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Advantages of mirrored pairs (0, 1), (2, 3), ...: half the return difference (+ for the better
    member); an unpaired last rollout, or a pair with a NaN return (a failed episode), gets 0. Divided by
    their root mean square over the pairs (if not 0 and ``normalize``)."""
    r = np.asarray(returns, dtype=np.float64)
    adv = np.zeros_like(r)
    m = len(r) // 2
    diff = 0.5 * (r[0 : 2 * m : 2] - r[1 : 2 * m : 2])
    diff[~np.isfinite(diff)] = 0.0
    adv[0 : 2 * m : 2] = diff
    adv[1 : 2 * m : 2] = -diff
    scale = float(np.sqrt(np.mean(diff * diff))) if m else 0.0
    return adv / scale if scale > 0.0 and normalize else adv


def pair_rms(advantages: np.ndarray) -> float:
    """Root mean square of the pairs' (raw) advantages: the size of this iteration's return differences."""
    a = np.asarray(advantages, dtype=np.float64)
    m = len(a) // 2
    return float(np.sqrt(np.mean(a[0 : 2 * m : 2] ** 2))) if m else 0.0
