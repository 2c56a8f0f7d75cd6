"""Action-noise PPO (the paper's): Gaussian force noise on the controller, PPO per decision.

One update per iteration: GAE with the linear feature baseline (predicted, then refitted on this
batch, in rllab's order), advantages standardised over the batch, minibatch epochs of the clipped
surrogate (``ppo.ppo_update``). The noise is not covered by the stability proof; only the
deterministic controller is.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from nf_core.policy_params import PolicyParameters

from .config import TrainConfig
from .mlp_policy import MLPPolicy
from .policy import NFPolicy
from .ppo import (
    LinearFeatureBaseline,
    PPOBatch,
    PPOSettings,
    compute_gae,
    discounted_returns,
    make_optimizer,
    normalize_advantages,
    ppo_update,
)
from .rollout import EpisodeRecord


class ActionNoisePPO:
    """The action-noise update of one run: its optimiser and baseline."""

    def __init__(self, cfg: TrainConfig, policy: NFPolicy | MLPPolicy, x_ref: np.ndarray) -> None:
        self.cfg = cfg
        self.policy = policy
        self.x_ref = x_ref
        self.baseline = LinearFeatureBaseline()
        self.optimizer = make_optimizer(list(policy.parameters()), cfg.learning_rate)
        self.settings = PPOSettings(cfg.update_epochs, cfg.minibatch_size, cfg.clip_coef,
                                    target_kl=cfg.update_target_kl)

    @staticmethod
    def plan(seeds: list[tuple[int, int]], rng: np.random.Generator
             ) -> list[tuple[int, int, PolicyParameters | None]]:
        """Each rollout runs the policy with noise: no parameters of its own."""
        return [(start, noise, None) for start, noise in seeds]

    def make_batch(self, episodes: list[EpisodeRecord]) -> PPOBatch:
        """Advantages from GAE with the baseline (predicted, then refitted on this batch), as tensors."""
        cfg = self.cfg
        cat = np.concatenate
        x, xdot = cat([e.x for e in episodes]), cat([e.xdot for e in episodes])
        t = cat([e.t for e in episodes])
        rewards = cat([e.reward for e in episodes])
        dones = cat([np.arange(len(e.reward)) == len(e.reward) - 1 for e in episodes])
        obs = np.concatenate([x - self.x_ref, xdot], axis=1)
        mc_returns = discounted_returns(rewards, dones, cfg.gamma)
        values = self.baseline.predict(obs, t)
        adv, returns = compute_gae(rewards, values, dones, cfg.gamma, cfg.gae_lambda)
        self.baseline.fit(obs, t, mc_returns)  # rllab order: this batch's fit serves the next one
        adv = normalize_advantages(adv)
        as_t = torch.from_numpy
        return PPOBatch(
            x=as_t(x), xdot=as_t(xdot), action=as_t(cat([e.action for e in episodes])),
            old_log_prob=as_t(cat([e.log_prob for e in episodes])), advantages=as_t(adv), returns=as_t(returns),
        )

    def update(self, episodes: list[EpisodeRecord | None], rng: np.random.Generator) -> tuple[dict[str, float], int]:
        """One PPO update from the iteration's episodes (None entries are skipped); its statistics and the
        number of decisions used."""
        batch = self.make_batch([e for e in episodes if e is not None])
        stats = ppo_update(self.policy, self.optimizer, batch, self.settings, rng)
        if isinstance(self.policy, NFPolicy):
            self.policy.sync_gains()
        return stats, len(batch)

    def state_dict(self) -> dict[str, Any]:
        """The optimiser's and the baseline's state (checkpoint keys ``optimizer``, ``baseline``)."""
        return {"optimizer": self.optimizer.state_dict(), "baseline": self.baseline.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict``'s keys."""
        self.optimizer.load_state_dict(state["optimizer"])
        self.baseline.load_state_dict(state["baseline"])
