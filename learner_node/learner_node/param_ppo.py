"""Parameter-space PPO: every rollout runs a deterministic stable controller drawn around the policy.

One update per iteration: mirrored pairs' advantages (scaled by their running RMS), PPO's clipped
surrogate per explored group (gains, flow) over rollouts, the optional cross-entropy step
(``param_elite``) and the spread schedule (``spread.settle_factor``). The distribution itself is
``param_explore.ParamExploration``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from nf_core.policy_params import PolicyParameters

from .config import TrainConfig
from .param_explore import ParamExploration, paired_advantages
from .policy import NFPolicy
from .ppo import approx_kl, clipped_surrogate_loss
from .rollout import EpisodeRecord
from .spread import settle_factor


def make_param_optimizer(explorer: ParamExploration, lr: float, sigma_lr: float) -> torch.optim.Adam:
    """Adam over the mean (each group's step ``lr`` times its current std, ``follow_sigma``) and the
    log-stds (step ``sigma_lr``; 0: the stds are not optimised)."""
    groups = []
    pol = explorer.policy[0]
    if explorer.explore_gains:
        sg = float(torch.exp(explorer.log_sigma_gains.detach()).mean())
        groups.append({"params": [pol.ln_s, pol.ln_d], "lr": lr * sg, "std_of": "gains"})
        if sigma_lr > 0.0:
            groups.append({"params": [explorer.log_sigma_gains], "lr": sigma_lr})
    if explorer.explore_flow:
        sf = float(torch.exp(explorer.log_sigma_flow.detach())[0])
        groups.append({"params": [explorer.flow_mu], "lr": lr * sf, "std_of": "flow"})
        if sigma_lr > 0.0:
            groups.append({"params": [explorer.log_sigma_flow], "lr": sigma_lr})
    return torch.optim.Adam(groups)


def follow_sigma(explorer: ParamExploration, optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Set each group's mean step to ``lr`` times the group's current std: one update moves the mean by
    the same number of stds (and about the same KL) late in a run as early, however the spread narrowed."""
    with torch.no_grad():
        std = {"gains": explorer.log_sigma_gains, "flow": explorer.log_sigma_flow}
        for group in optimizer.param_groups:
            which = group.get("std_of")
            if which is not None and std[which].numel():
                group["lr"] = lr * float(torch.exp(std[which]).mean())


def param_ppo_update(
    explorer: ParamExploration, optimizer: torch.optim.Optimizer, theta: np.ndarray, advantages: np.ndarray,
    epochs: int, clip_coef: float, target_kl: float = 0.0,
) -> dict[str, float]:
    """``epochs`` full-batch steps of PPO's clipped surrogate over rollouts (one action per rollout: its
    parameter vector), one surrogate and ratio per explored group (gains, flow; the distribution
    factorises), summed; stops early once approx_kl exceeds 1.5 x ``target_kl`` (0: never)."""
    th = torch.from_numpy(np.asarray(theta, dtype=np.float64))
    adv = torch.from_numpy(np.asarray(advantages, dtype=np.float64))
    with torch.no_grad():
        old = explorer.group_log_probs(th)
    limit = 1.5 * target_kl if target_kl > 0.0 else math.inf
    losses, clips, run = [], [], 0
    for _ in range(epochs):
        new = explorer.group_log_probs(th)
        with torch.no_grad():
            if sum(float(approx_kl(n, o)) for n, o in zip(new, old, strict=True)) > limit:
                break
        parts = [clipped_surrogate_loss(n, o, adv, clip_coef) for n, o in zip(new, old, strict=True)]
        loss = sum(p[0] for p in parts)
        clip_frac = max(float(p[1]) for p in parts)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        run += 1
        losses.append(float(loss.detach()))
        clips.append(float(clip_frac))
    explorer.sync_policy()
    with torch.no_grad():
        kl = sum(float(approx_kl(n, o)) for n, o in zip(explorer.group_log_probs(th), old, strict=True))
    return {
        "pg_loss": float(np.mean(losses)) if losses else math.nan,
        "v_loss": math.nan,
        "clip_frac": float(np.mean(clips)) if clips else math.nan,
        "approx_kl": kl,
        "epochs": float(run),
    }


class ParamSpacePPO:
    """The parameter-space update of one run: its distribution, optimiser and this iteration's draws."""

    def __init__(self, cfg: TrainConfig, policy: NFPolicy) -> None:
        self.cfg = cfg
        self.explorer = ParamExploration(policy, cfg.param_sigma_gains, cfg.param_sigma_flow, cfg.flow_input_scale,
                                         cfg.param_flow_dim, cfg.seed)
        self.optimizer = make_param_optimizer(self.explorer, cfg.param_lr, cfg.param_sigma_lr)
        self.pending: np.ndarray | None = None  # this iteration's parameter draws

    def plan(self, seeds: list[tuple[int, int]], rng: np.random.Generator
             ) -> list[tuple[int, int, PolicyParameters | None]]:
        """Mirrored pairs of parameter draws, the second of a pair on the first's start; kept for ``update``."""
        theta, _ = self.explorer.sample(len(seeds), rng)
        self.pending = theta
        seeds = list(seeds)
        for i in range(1, 2 * (len(seeds) // 2), 2):
            seeds[i] = (seeds[i - 1][0], seeds[i][1])
        return [(start, noise, self.explorer.params_for(th)) for (start, noise), th in zip(seeds, theta, strict=True)]

    def update(self, episodes: list[EpisodeRecord | None], rng: np.random.Generator) -> tuple[dict[str, float], int]:
        """One update from the episodes of ``plan()``, in its order (None: a failed one; its pair does not
        count). Returns the update's statistics and the number of decisions used."""
        cfg = self.cfg
        if self.pending is None or len(self.pending) != len(episodes):
            raise ValueError("params exploration: update() needs the episodes of episode_plan(), in order")
        follow_sigma(self.explorer, self.optimizer, cfg.param_lr)
        returns = np.array([np.nan if e is None else e.episode_return for e in episodes])
        adv = paired_advantages(returns, normalize=False)
        scale = self.explorer.running_scale(adv)
        if scale > 0.0:
            adv = adv / scale
        ran = [e for e in episodes if e is not None]
        if not ran:
            raise ValueError("params exploration: every episode failed")
        stats = param_ppo_update(self.explorer, self.optimizer, self.pending, adv, cfg.update_epochs, cfg.clip_coef,
                                 cfg.update_target_kl)
        if cfg.param_elite != "none":
            stats["param_elite"] = float(self.elite_step(episodes))
        self.explorer.decay(cfg.param_sigma_decay)
        settle = settle_factor(cfg, episodes)
        self.explorer.decay(settle)
        if cfg.param_sigma_settle < 1.0:
            stats["param_settled"] = float(settle < 1.0)
        self.pending = None
        return stats, sum(len(e.reward) for e in ran)

    def elite_step(self, episodes: list[EpisodeRecord | None]) -> int:
        """``param_elite`` minority_returns, after PPO's step: while some rollouts (the mean's, the odd last
        one, included) inserted but fewer than half, move the mean to their average and multiply the stds by
        ``param_sigma_jump``; while none inserted, to the best quarter of the draws by return if each beat
        the mean's own rollout. Returns the number of rollouts averaged (0: no move)."""
        if len(episodes) % 2 == 0 or episodes[-1] is None:
            return 0
        won = [i for i, e in enumerate(episodes) if e is not None and e.final_success]
        if 2 * len(won) >= sum(e is not None for e in episodes):
            return 0
        by_return = not won
        if by_return:
            won = better_by_return(episodes)
        if not won:
            return 0
        self.explorer.set_mean(np.mean(self.pending[won], axis=0))
        self.explorer.sync_policy()
        if not by_return:
            self.explorer.decay(self.cfg.param_sigma_jump)
        return len(won)

    def restart_optimizer(self) -> None:
        """A new optimiser for the distribution as it is now (after a loaded policy or spread)."""
        self.optimizer = make_param_optimizer(self.explorer, self.cfg.param_lr, self.cfg.param_sigma_lr)

    def state_dict(self) -> dict[str, Any]:
        """The optimiser's and the distribution's state (checkpoint keys ``optimizer``, ``explorer``)."""
        return {"optimizer": self.optimizer.state_dict(), "explorer": self.explorer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict``'s keys."""
        shape = tuple(self.explorer.flow_basis.shape)
        self.explorer.load_state_dict(state["explorer"])
        if tuple(self.explorer.flow_basis.shape) != shape:  # another basis (use_basis): a new mean parameter
            self.restart_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])


def better_by_return(episodes: list[EpisodeRecord | None]) -> list[int]:
    """The best quarter of the draws by return if each of them beat the mean's own rollout (the last), else none."""
    draws = sorted(((e.episode_return, i) for i, e in enumerate(episodes[:-1]) if e is not None), reverse=True)
    top = draws[:max(1, len(draws) // 4)]
    return [i for _, i in top] if top and top[-1][0] > episodes[-1].episode_return else []
