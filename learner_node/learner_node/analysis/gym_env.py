"""Gymnasium view of the trainer's insertion task (``DecisionEnv``), for stable-baselines3 in bench/.

Bench/dev only: gymnasium comes with ``requirements/bench.txt`` (``make bench`` installs it); the
rest of the project does not import this module. Spaces are float64 like the trainer's arrays:
observation ``[x - x_ref, xdot]`` (m, m/s; unbounded), action the task-space force (N) in
``[-force_limit, force_limit]`` per axis (stable-baselines3 clips its samples to the box). The
episode's time limit ends it with ``truncated`` (never ``terminated``). ``reset(seed=s)`` starts
from the trainer's start seed ``s``; an unseeded reset draws the start seed from ``np_random``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium
import numpy as np

from ..config import TrainConfig
from ..trainer import EVAL_SEED_BASE
from .decision_env import DecisionEnv

FORCE_LIMIT = 100.0  # N per axis; at the Panda's ~0.9 m reach that is its 87 Nm joint torque limit


class InsertionGymEnv(gymnasium.Env):
    """``gymnasium.Env`` over ``DecisionEnv(cfg)``: one step = one decision period with a held force."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, cfg: TrainConfig, force_limit: float = FORCE_LIMIT) -> None:
        self.core = DecisionEnv(cfg)
        d = self.core.dim
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(2 * d,), dtype=np.float64)
        self.action_space = gymnasium.spaces.Box(-force_limit, force_limit, shape=(d,), dtype=np.float64)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """New episode from start seed ``seed`` (a training start seed drawn from ``np_random`` if None)."""
        super().reset(seed=seed)
        start = seed if seed is not None else int(self.np_random.integers(0, EVAL_SEED_BASE))
        return self.core.reset(start), {"start_seed": start}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hold the force ``action`` for one decision period: (obs, reward, terminated, truncated, info)."""
        obs, reward, over, info = self.core.step(action)
        return obs, reward, False, over, info
