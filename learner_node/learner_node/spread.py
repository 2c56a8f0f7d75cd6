"""The spread schedule of parameter exploration: how much the exploration stds narrow after an update."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .config import TrainConfig
from .rollout import EpisodeRecord

SETTLE_BELOW = 0.9  # the spread settles only while fewer than this share of the rollouts insert


def settle_factor(cfg: TrainConfig, episodes: Sequence[EpisodeRecord | None]) -> float:
    """``param_sigma_settle`` when the spread should narrow after this update, else 1.

    Rule ``mean``: the mean's own rollout (the odd last one) inserted while fewer than 90 % of the draws
    did (the failing draws are only spread). Rule ``batch``: the batch success rate is in
    [``param_settle_from``, 90 %) (random starts: one rollout of the mean says little)."""
    factor = cfg.param_sigma_settle
    if factor >= 1.0:
        return 1.0
    if cfg.param_settle_rule == "batch":
        ran = [e.final_success for e in episodes if e is not None]
        rate = float(np.mean(ran)) if ran else 0.0
        return factor if cfg.param_settle_from <= rate < SETTLE_BELOW else 1.0
    if len(episodes) % 2 == 0 or episodes[-1] is None:
        return 1.0
    draws = [e.final_success for e in episodes[:-1] if e is not None]
    if episodes[-1].final_success and draws and float(np.mean(draws)) < SETTLE_BELOW:
        return factor
    return 1.0
