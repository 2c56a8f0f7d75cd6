"""The task reward. ROS-free, no torch.

Shared by the in-process rollouts (``learner_node.rollout``) and the controller node, which
computes the same numbers when it streams a rollout over ROS. Reward of one decision, from the
state at the end of its period (the paper's reward, Khader et al., ICRA 2021)::

    r = -w |d|^2 - v ln((|d|^2 + a) / a) - c_v |xdot|^2 - c_u |action|^2,   d = x - x_goal
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

REWARD_TERMS = ("distance", "log_distance", "velocity", "action")


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (see the module docstring); the task's reward uses the defaults."""

    w: float = 1.0  # squared distance, 1/m^2
    v: float = 2.0  # log-distance
    a: float = 1e-5  # log offset, m^2
    velocity: float = 0.1  # squared speed, 1/(m/s)^2
    action: float = 1e-3  # squared force, 1/N^2

    def check(self) -> None:
        """Raise ``ValueError`` for negative weights or a non-positive offset."""
        for name in ("w", "v", "velocity", "action"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"reward weight {name} must be >= 0, got {getattr(self, name)}")
        if not self.a > 0.0:
            raise ValueError(f"reward offset a must be > 0, got {self.a}")


DEFAULT_WEIGHTS = RewardWeights()


def reward_terms(d: np.ndarray, xdot: np.ndarray, action: np.ndarray, weights: RewardWeights) -> dict[str, np.ndarray]:
    """The reward's terms (each <= 0) for rows of distance vectors d (m), velocities (m/s), actions (N)."""
    d2 = np.sum(np.square(d), axis=-1)
    return {
        "distance": -weights.w * d2,
        "log_distance": -weights.v * (np.log(d2 + weights.a) - math.log(weights.a)),
        "velocity": -weights.velocity * np.sum(np.square(xdot), axis=-1),
        "action": -weights.action * np.sum(np.square(action), axis=-1),
    }
