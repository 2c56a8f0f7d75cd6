"""make run's GIF is the evaluation's episode: rendered from the first held-out start with the run's own
policy and law (here a stiff prior whose pull the potential's bound limits), it ends as the deterministic
evaluation of that start does."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from learner_node.analysis.video import render_run_gif
from learner_node.config import TrainConfig
from learner_node.trainer import EVAL_SEED_BASE, Trainer

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_learn.yaml"


def test_the_gif_ends_as_the_evaluation_of_the_same_start(tmp_path):
    cfg = TrainConfig.from_sources(CONFIG, {"stiffness": 1500.0, "potential_force_bound": 30.0, "eval_episodes": 1,
                                            "episode_seconds": 2.0})
    trainer = Trainer(cfg)
    evaluation = trainer.evaluate()["per_episode"][0]
    info = render_run_gif(trainer, tmp_path / "final_policy.gif", EVAL_SEED_BASE, fps=10.0, width=96, height=72)
    assert (tmp_path / "final_policy.gif").stat().st_size > 0 and info["frames"] >= 19
    assert info["success"] == evaluation["success"]
    np.testing.assert_allclose(info["max_depth"], evaluation["max_depth"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(info["final_distance"], evaluation["final_distance"], rtol=0, atol=1e-12)
    # the check can fail: without the bound the same start ends elsewhere
    unbounded = Trainer(TrainConfig.from_sources(CONFIG, {"stiffness": 1500.0, "potential_force_bound": 0.0,
                                                          "eval_episodes": 1, "episode_seconds": 2.0}))
    other = unbounded.evaluate()["per_episode"][0]
    assert abs(other["final_distance"] - evaluation["final_distance"]) > 1e-6
