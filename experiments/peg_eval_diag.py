"""Peg seeds 1 and 2 (final policies): re-run the held-out evaluation episode both fail (start
1000000004, EVAL_SEED_BASE + 4) and print where the arm ends: the peg's offset from the goal and the
joints against the Panda's limits. Run from the repository root after the runs of
docs/results/peg_learned (needs runs/learn_peg)."""
import numpy as np

from learner_node.config import TrainConfig
from learner_node.trainer import EVAL_SEED_BASE, Trainer, make_evaluator
from nf_core import panda_spec

SETS = dict(stiffness_axial="none", flow_init="identity", gains="learned", exploration="params",
            param_sigma_gains="0.5", param_lr="0.1", param_sigma_lr="0.01", param_sigma_decay="0.97",
            policy="nf", sigma_init="1", iterations="30")
START = 4

for seed in (1, 2):
    trainer = Trainer(TrainConfig.from_sources("config/peg.yaml", dict(SETS, seed=str(seed))))
    trainer.load_checkpoint(f"runs/learn_peg/peg/nf-sigma1-seed{seed}/checkpoint.pt")
    rec = trainer.runner.run_episode(make_evaluator(trainer.policy), None, EVAL_SEED_BASE + START, None)
    q = trainer.runner.env.q
    print("seed", seed, "success", rec.final_success, "final distance", rec.final_distance,
          "depth max", rec.depth.max())
    print("  x - x_goal (controller frame, last decision)", np.round(rec.x[-1] - np.asarray(trainer.x_ref), 4))
    print("  q", np.round(q, 3))
    print("  margin to Q_MIN", np.round(q - panda_spec.Q_MIN, 4))
    print("  margin to Q_MAX", np.round(panda_spec.Q_MAX - q, 4))
