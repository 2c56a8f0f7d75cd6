"""PPO pieces: returns, GAE, advantage normalisation, the clipped surrogate loss, baselines, the update.

Conventions: a batch is the concatenation of whole episodes, flat along the first axis;
``dones[t]`` is True when step t is the last step of its episode. Episodes end by the time limit;
they are treated as terminal (nothing is bootstrapped after the last step), as the authors'
linear baseline does (its time features let it predict the shrinking remaining return).

The functions are pure (numpy in, numpy out; or torch tensors for the losses) so the tests can
check them against small cases computed by hand.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import nn

# =====================================================================================================
# Returns and advantages
# =====================================================================================================


def discounted_returns(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = r_t + gamma G_{t+1} within each episode (G after an episode's last step is 0)."""
    rewards = np.asarray(rewards, dtype=np.float64)
    dones = np.asarray(dones, dtype=bool)
    out = np.empty_like(rewards)
    running = 0.0
    for t in range(rewards.shape[0] - 1, -1, -1):
        if dones[t]:
            running = 0.0
        running = rewards[t] + gamma * running
        out[t] = running
    return out


def compute_gae(
    rewards: np.ndarray,
    values: np.ndarray,
    dones: np.ndarray,
    gamma: float,
    lam: float,
    bootstrap: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation over back-to-back episodes; returns (advantages, returns).

    delta_t = r_t + gamma V_next(t) - V(s_t), A_t = delta_t + gamma lam A_{t+1} (A_{t+1} = 0 after an
    episode's last step). V_next(t) is ``values[t+1]`` inside an episode and, at an episode's last
    step, ``bootstrap[t]`` (the value of the state after it, for truncated episodes) or 0 when
    ``bootstrap`` is None (terminal). ``returns = advantages + values`` (the lambda-returns).
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    dones = np.asarray(dones, dtype=bool)
    n = rewards.shape[0]
    if values.shape != (n,) or dones.shape != (n,):
        raise ValueError(f"rewards, values, dones must all have shape ({n},): {values.shape}, {dones.shape}")
    if n and not dones[-1]:
        raise ValueError("the batch must end with an episode end (dones[-1] True)")
    adv = np.empty(n)
    last = 0.0
    for t in range(n - 1, -1, -1):
        if dones[t]:
            next_value = 0.0 if bootstrap is None else float(bootstrap[t])
            last = 0.0
        else:
            next_value = values[t + 1]
        delta = rewards[t] + gamma * next_value - values[t]
        last = delta + gamma * lam * last
        adv[t] = last
    return adv, adv + values


def normalize_advantages(adv: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Standardise advantages once over the whole batch (not per minibatch): (A - mean) / (std + eps),
    what the authors' rllab-style code calls centred advantages."""
    adv = np.asarray(adv, dtype=np.float64)
    return (adv - adv.mean()) / (adv.std() + eps)


# =====================================================================================================
# Losses
# =====================================================================================================


def approx_kl(new_log_prob: torch.Tensor, old_log_prob: torch.Tensor) -> torch.Tensor:
    """Estimate of KL(old || new) from samples of the old policy: mean((r - 1) - log r), r = p_new/p_old."""
    log_ratio = new_log_prob - old_log_prob
    return ((torch.exp(log_ratio) - 1.0) - log_ratio).mean()


def clipped_surrogate_loss(
    new_log_prob: torch.Tensor, old_log_prob: torch.Tensor, advantages: torch.Tensor, clip_coef: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO's clipped objective as a loss to minimise, and the fraction of samples whose ratio was clipped.

    loss = -mean(min(r A, clip(r, 1 - eps, 1 + eps) A)), r = exp(new_log_prob - old_log_prob).
    The advantages are used as given (normalise them beforehand with ``normalize_advantages``).
    """
    ratio = torch.exp(new_log_prob - old_log_prob)
    unclipped = ratio * advantages
    clipped = torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef) * advantages
    loss = -torch.minimum(unclipped, clipped).mean()
    clip_frac = ((ratio - 1.0).abs() > clip_coef).to(ratio.dtype).mean()
    return loss, clip_frac


# =====================================================================================================
# Baselines
# =====================================================================================================


class LinearFeatureBaseline:
    """Least-squares value baseline on features of the observation and time (the authors' choice).

    Features: [o, o^2, t, t^2, t^3, 1] with o the observation clipped to +-10 and t the time in the
    episode (s). ``fit`` solves ridge-regularised least squares to the targets (the ridge starts at
    1e-5 and grows tenfold until the solution is finite); before the first fit it predicts 0.
    """

    def __init__(self, reg_coeff: float = 1e-5) -> None:
        self.reg_coeff = reg_coeff
        self.coeffs: np.ndarray | None = None

    @staticmethod
    def features(obs: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Feature matrix (N, 2 * obs_dim + 4) for observations (N, obs_dim) and times (N,)."""
        o = np.clip(np.asarray(obs, dtype=np.float64), -10.0, 10.0)
        t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
        return np.concatenate([o, o * o, t, t * t, t**3, np.ones_like(t)], axis=1)

    def fit(self, obs: np.ndarray, t: np.ndarray, targets: np.ndarray) -> None:
        """Refit the coefficients to ``targets`` (N,)."""
        F = self.features(obs, t)
        y = np.asarray(targets, dtype=np.float64)
        reg = self.reg_coeff
        A, b = F.T @ F, F.T @ y
        eye = np.eye(F.shape[1])
        for _ in range(5):
            try:
                coeffs = np.linalg.solve(A + reg * eye, b)
            except np.linalg.LinAlgError:
                coeffs = np.full(F.shape[1], np.nan)
            if np.all(np.isfinite(coeffs)):
                self.coeffs = coeffs
                return
            reg *= 10.0
        raise FloatingPointError("linear baseline: no finite least-squares solution")

    def predict(self, obs: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Predicted values (N,)."""
        if self.coeffs is None:
            return np.zeros(np.asarray(obs).shape[0])
        return self.features(obs, t) @ self.coeffs

    def state_dict(self) -> dict[str, torch.Tensor | None]:
        """Coefficients as a tensor (for torch.save)."""
        return {"coeffs": None if self.coeffs is None else torch.from_numpy(self.coeffs.copy())}

    def load_state_dict(self, state: dict[str, torch.Tensor | None]) -> None:
        """Restore from ``state_dict``."""
        c = state["coeffs"]
        self.coeffs = None if c is None else c.numpy().astype(np.float64).copy()


class GaussianPolicy(Protocol):
    """What the update needs from a policy (``NFPolicy`` and ``MLPPolicy`` both have it)."""

    def log_prob(self, x: torch.Tensor, xdot: torch.Tensor, action: torch.Tensor) -> torch.Tensor: ...

    def parameters(self) -> Iterable[nn.Parameter]: ...


@dataclass
class PPOBatch:
    """One iteration's decisions (tensors, first axis = decision)."""

    x: torch.Tensor  # (N, d) task-space position the controller saw, m
    xdot: torch.Tensor  # (N, d) task-space velocity, m/s
    action: torch.Tensor  # (N, d) mean force + held noise, N
    old_log_prob: torch.Tensor  # (N,) log-density of the action under the behaviour policy
    advantages: torch.Tensor  # (N,) normalised advantages
    returns: torch.Tensor  # (N,) GAE returns (advantages + baseline)

    def __len__(self) -> int:
        return self.x.shape[0]


@dataclass
class PPOSettings:
    """Update settings (a subset of ``TrainConfig``)."""

    update_epochs: int = 10
    minibatch_size: int = 64
    clip_coef: float = 0.2
    target_kl: float = 0.0  # 0: off


def make_optimizer(params: Iterable[nn.Parameter], lr: float) -> torch.optim.Adam:
    """Adam for the PPO update, in torch's fused implementation (one kernel per tensor per step).

    Same algorithm and hyper-parameters as the default implementation (which differs only in
    rounding); the default loops over tensors in Python, a dozen small ops each, which dominates
    a minibatch step for the NF policy's 49 small parameter arrays.
    """
    return torch.optim.Adam(params, lr=lr, fused=True)


def ppo_update(
    policy: GaussianPolicy,
    optimizer: torch.optim.Optimizer,
    batch: PPOBatch,
    settings: PPOSettings,
    rng: np.random.Generator,
) -> dict[str, float]:
    """Minibatch epochs of the clipped PPO loss (the baseline is fitted outside: no value loss).

    Each epoch visits a fresh permutation from ``rng`` in minibatches of ``minibatch_size`` (the last
    one may be smaller). Reports the mean policy loss, value loss and clip fraction over all
    minibatches, the epochs begun, and ``approx_kl``: KL(old || new) estimated over the whole batch
    after the update. With ``target_kl`` the update stops before the first minibatch step whose
    minibatch already shows an approx_kl above 1.5 x target_kl (stable-baselines3's rule).
    """
    n = len(batch)
    pg_losses, clip_fracs = [], []
    epochs_run = 0
    kl_limit = 1.5 * settings.target_kl if settings.target_kl > 0.0 else math.inf
    stop = False
    for _ in range(settings.update_epochs):
        perm = torch.from_numpy(rng.permutation(n))
        epochs_run += 1
        for start in range(0, n, settings.minibatch_size):
            idx = perm[start : start + settings.minibatch_size]
            new_lp = policy.log_prob(batch.x[idx], batch.xdot[idx], batch.action[idx])
            with torch.no_grad():  # how far the steps so far have moved the policy, on fresh samples
                if float(approx_kl(new_lp, batch.old_log_prob[idx])) > kl_limit:
                    stop = True
                    break
            pg_loss, clip_frac = clipped_surrogate_loss(
                new_lp, batch.old_log_prob[idx], batch.advantages[idx], settings.clip_coef
            )
            optimizer.zero_grad()
            pg_loss.backward()
            optimizer.step()
            pg_losses.append(float(pg_loss.detach()))
            clip_fracs.append(float(clip_frac))
        if stop:
            break
    with torch.no_grad():
        kl = float(approx_kl(policy.log_prob(batch.x, batch.xdot, batch.action), batch.old_log_prob))
    return {
        "pg_loss": float(np.mean(pg_losses)) if pg_losses else math.nan,
        "v_loss": math.nan,
        "clip_frac": float(np.mean(clip_fracs)) if clip_fracs else math.nan,
        "approx_kl": kl,
        "epochs": float(epochs_run),
    }
