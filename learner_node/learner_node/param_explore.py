"""Exploration in parameter space for the NF policy: every rollout is a deterministic stable controller.

Instead of adding force noise to the controller's output, each rollout of an iteration runs the
deterministic flow controller with its own parameters theta drawn around the policy's
(``theta = mu + sigma * eps``): the log-diagonals of S and D (``gains="learned"``) and, if
``param_sigma_flow > 0``, every flow weight. Whatever theta is drawn, S and D stay symmetric
positive definite and phi a bijection, so each exploration rollout is itself a provably stable,
passive closed loop; and the exploration is coherent over the whole trajectory (a 1 N force
sample held 10 ms barely moves the gear; a 30 % softer axis acts for five seconds).

Rollouts come in mirrored pairs ``mu +- sigma eps`` from the same start (an odd last rollout runs
``mu`` itself), so a pair's return difference is due to its parameters alone, not to its start:
the advantage of each member is half the difference (Sehnke et al.'s symmetric sampling). The
update is PPO's clipped surrogate over rollouts, with log-probability the Gaussian density of
theta, for the mean (the policy's own parameters) and the per-group log-std.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import nn

from nf_core.policy_params import PolicyParameters

from .policy import LN_MAX_DAMPING, LN_MAX_STIFFNESS, NFPolicy
from .ppo import approx_kl, clipped_surrogate_loss

_LOG_2PI = math.log(2.0 * math.pi)


class ParamExploration(nn.Module):
    """Gaussian distribution over the explored parameters of an ``NFPolicy`` (mean = the policy's own)."""

    def __init__(self, policy: NFPolicy, sigma_gains: float, sigma_flow: float) -> None:
        """Explore ln S, ln D (if the policy learns its gains) with std ``sigma_gains`` per entry, and
        every flow weight with one shared std ``sigma_flow`` (if > 0)."""
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
        self.n_flow = policy.arch.n_params if self.explore_flow else 0

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
            out += pol.flow.param_list()
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
            changes["stiffness"] = np.diag(np.exp(np.minimum(theta[:d], LN_MAX_STIFFNESS)))
            changes["damping"] = np.diag(np.exp(np.minimum(theta[d : 2 * d], LN_MAX_DAMPING)))
        if self.explore_flow:
            changes["weights"] = np.asarray(theta[self.n_gain :], dtype=np.float64).copy()
        return dataclasses.replace(base, **changes)

    def decay(self, factor: float) -> None:
        """Multiply every exploration std by ``factor``."""
        if factor != 1.0:
            with torch.no_grad():
                self.log_sigma_gains.add_(math.log(factor))
                self.log_sigma_flow.add_(math.log(factor))

    def log_prob(self, theta: torch.Tensor) -> torch.Tensor:
        """Gaussian log-density of each row of ``theta`` (K, dim), differentiable in mu and the log-stds."""
        mu, sig = self.mean(), self.sigma()
        z = (theta - mu) / sig
        return -0.5 * (z * z).sum(dim=1) - torch.log(sig).sum() - 0.5 * self.dim * _LOG_2PI


def paired_advantages(returns: np.ndarray) -> np.ndarray:
    """Advantages of mirrored pairs (0, 1), (2, 3), ...: half the return difference (+ for the better
    member); an unpaired last rollout, or a pair with a NaN return (a failed episode), gets 0. Divided by
    their root mean square over the pairs (if not 0)."""
    r = np.asarray(returns, dtype=np.float64)
    adv = np.zeros_like(r)
    m = len(r) // 2
    diff = 0.5 * (r[0 : 2 * m : 2] - r[1 : 2 * m : 2])
    diff[~np.isfinite(diff)] = 0.0
    adv[0 : 2 * m : 2] = diff
    adv[1 : 2 * m : 2] = -diff
    scale = float(np.sqrt(np.mean(diff * diff))) if m else 0.0
    return adv / scale if scale > 0.0 else adv


def make_param_optimizer(explorer: ParamExploration, lr: float, sigma_lr: float) -> torch.optim.Adam:
    """Adam with steps scaled per group: the mean moves by about ``lr`` of its (initial) std per step, the
    log-stds by ``sigma_lr`` (0: not optimised, the stds stay as initialised)."""
    groups = []
    pol = explorer.policy[0]
    if explorer.explore_gains:
        sg = float(torch.exp(explorer.log_sigma_gains.detach()).mean())
        groups.append({"params": [pol.ln_s, pol.ln_d], "lr": lr * sg})
        if sigma_lr > 0.0:
            groups.append({"params": [explorer.log_sigma_gains], "lr": sigma_lr})
    if explorer.explore_flow:
        sf = float(torch.exp(explorer.log_sigma_flow.detach())[0])
        groups.append({"params": pol.flow.param_list(), "lr": lr * sf})
        if sigma_lr > 0.0:
            groups.append({"params": [explorer.log_sigma_flow], "lr": sigma_lr})
    return torch.optim.Adam(groups)


def param_ppo_update(
    explorer: ParamExploration,
    optimizer: torch.optim.Optimizer,
    theta: np.ndarray,
    advantages: np.ndarray,
    epochs: int,
    clip_coef: float,
    target_kl: float = 0.0,
) -> dict[str, float]:
    """``epochs`` full-batch steps of PPO's clipped surrogate over rollouts (one action per rollout:
    its parameter vector); stops early like ``ppo_update`` when approx_kl exceeds 1.5 x target_kl."""
    th = torch.from_numpy(np.asarray(theta, dtype=np.float64))
    adv = torch.from_numpy(np.asarray(advantages, dtype=np.float64))
    with torch.no_grad():
        old = explorer.log_prob(th)
    limit = 1.5 * target_kl if target_kl > 0.0 else math.inf
    losses, clips, run = [], [], 0
    for _ in range(epochs):
        new = explorer.log_prob(th)
        with torch.no_grad():
            if float(approx_kl(new, old)) > limit:
                break
        loss, clip_frac = clipped_surrogate_loss(new, old, adv, clip_coef)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        run += 1
        losses.append(float(loss.detach()))
        clips.append(float(clip_frac))
    explorer.policy[0].sync_gains()
    with torch.no_grad():
        kl = float(approx_kl(explorer.log_prob(th), old))
    return {
        "pg_loss": float(np.mean(losses)) if losses else math.nan,
        "v_loss": math.nan,
        "clip_frac": float(np.mean(clips)) if clips else math.nan,
        "approx_kl": kl,
        "epochs": float(run),
    }
