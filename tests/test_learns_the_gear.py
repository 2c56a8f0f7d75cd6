"""make run's task is learned: in process, config/gear_learn.yaml from its failing prior (seed 0). The
deterministic controller inserts at most 2 of 10 held-out starts before and at least 8 of 10 after
12 iterations, and the training success rises."""

from __future__ import annotations

from pathlib import Path

from learner_node.config import TrainConfig
from learner_node.trainer import Trainer

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_learn.yaml"


def test_the_gear_is_learned_from_the_failing_prior():
    trainer = Trainer(TrainConfig.from_sources(CONFIG, {"iterations": 12}))
    prior = trainer.evaluate()
    learned = trainer.run(evaluate=True, evaluate_prior=False)
    success = [row["success_rate"] for row in trainer.history]
    assert prior["success_rate"] <= 0.2, prior["success_rate"]
    assert max(success[-3:]) >= 0.6 and success[-1] > success[0], success
    assert learned["success_rate"] >= 0.8, (learned["success_rate"], success)
