"""The task reward. ROS-free, no torch.

Shared by the in-process rollouts (``learner_node.rollout``) and the controller node, which
computes the same numbers when it streams a rollout over ROS. Reward of one decision, from the
state at the end of its period (the paper's reward, Khader et al., ICRA 2021)::

    r = -w |d|^2 - v ln((|d|^2 + a) / a) - c_v |xdot|^2 - c_u |action|^2,   d = x - x_goal
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

REWARD_TERMS = ("distance", "log_distance", "velocity", "action")


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (see the module docstring)."""

    w: float = 1.0  # squared distance, 1/m^2
    v: float = 2.0  # log-distance
    a: float = 1e-5  # log offset, m^2
    velocity: float = 0.1  # squared speed, 1/(m/s)^2
    action: float = 1e-3  # squared force, 1/N^2

    @classmethod
    def from_config(cls, cfg: Any) -> RewardWeights:
        """The weights of anything with ``reward_w``, ``reward_v``, ``reward_a``, ``reward_velocity``,
        ``reward_action`` attributes (a ``TrainConfig``)."""
        return cls(*(getattr(cfg, f"reward_{name}") for name in REWARD_PARAMETERS))

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> RewardWeights:
        """The weights of a node's parameters (keys ``reward_w``, ..., ``reward_action``)."""
        return cls(*(params[f"reward_{name}"] for name in REWARD_PARAMETERS))

    def check(self) -> None:
        """Raise ``ValueError`` for negative weights or a non-positive offset."""
        for name in ("w", "v", "velocity", "action"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"reward weight {name} must be >= 0, got {getattr(self, name)}")
        if not self.a > 0.0:
            raise ValueError(f"reward offset a must be > 0, got {self.a}")


# The weights as node parameters and config fields (``reward_<field>``): the one place their
# defaults and meanings are written.
REWARD_PARAMETERS = {
    "w": "reward: weight of |d|^2 (d in m)",
    "v": "reward: weight of ln((|d|^2 + a) / a)",
    "a": "reward: offset a of the log-distance term, m^2 (sets where it saturates, ~3 mm)",
    "velocity": "reward: weight of the squared TCP speed |xdot|^2 (m/s)",
    "action": "reward: weight of the squared action force |u|^2 (N)",
}
DEFAULT_WEIGHTS = RewardWeights()


def reward_parameter_defaults() -> dict[str, tuple[float, str]]:
    """``reward_<field>`` -> (default, description), for a node's parameter table."""
    return {f"reward_{name}": (getattr(DEFAULT_WEIGHTS, name), doc) for name, doc in REWARD_PARAMETERS.items()}


def reward_terms(d: np.ndarray, xdot: np.ndarray, action: np.ndarray, weights: RewardWeights) -> dict[str, np.ndarray]:
    """The reward's terms (each <= 0) for rows of distance vectors d (m), velocities (m/s), actions (N)."""
    d2 = np.sum(np.square(d), axis=-1)
    return {
        "distance": -weights.w * d2,
        "log_distance": -weights.v * (np.log(d2 + weights.a) - math.log(weights.a)),
        "velocity": -weights.velocity * np.sum(np.square(xdot), axis=-1),
        "action": -weights.action * np.sum(np.square(action), axis=-1),
    }
