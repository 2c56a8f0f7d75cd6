"""Peg seed 1 (final policy), re-run of learner_node.analysis.report's free-space check from start 1000000004
(EVAL_SEED_BASE + 4): where the arm ends, its joints against the Panda's limits and its torques.
Run from the repository root after the runs of docs/results/peg_learned (needs runs/learn_peg)."""
import numpy as np

from learner_node.config import TrainConfig
from learner_node.trainer import EVAL_SEED_BASE, Trainer, make_evaluator
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_core import panda_spec
from sim_bridge_node.env import InsertionEnv

SETS = dict(stiffness_axial="none", flow_init="identity", gains="learned", exploration="params",
            param_sigma_gains="0.5", param_lr="0.1", param_sigma_lr="0.01", param_sigma_decay="0.97",
            policy="nf", sigma_init="1", seed="1", iterations="30")
START = 4  # the report's 5th free-space start

trainer = Trainer(TrainConfig.from_sources("config/peg.yaml", SETS))
trainer.load_checkpoint("runs/learn_peg/peg/nf-sigma1-seed1/checkpoint.pt")
policy = trainer.policy
env = InsertionEnv("free")  # as in learner_node.analysis.report.freespace_check: the free scene's hand holds the gear
ctrl = FlowController(ArmModel(part=panda_spec.GEAR_PART), make_evaluator(policy))
x_ref = policy.x_ref.detach().numpy().copy()

env.reset(seed=EVAL_SEED_BASE + START)
ctrl.reset_rate_limit()
ctrl.clear_fault()
q0 = env.q.copy()
saturated_ms = 0
for i in range(10000):  # 10 s at 1 kHz, as the report's check
    tau = ctrl.step(env.q, env.dq)
    if np.any(np.abs(tau) >= panda_spec.TORQUE_LIMITS - 1e-6):
        saturated_ms += 1
    env.step(tau)
    if i % 2000 == 1999:
        dist, speed = np.linalg.norm(env.x - x_ref), np.linalg.norm(env.xdot)
        print(f"t={(i + 1) / 1000:.0f}s dist={dist:.4f} m speed={speed:.2e} m/s")
q = env.q
print("start", EVAL_SEED_BASE + START, "iteration", trainer.iteration)
print("final distance", np.linalg.norm(env.x - x_ref), "x - x_ref", env.x - x_ref)
print("q0", np.round(q0, 3))
print("q ", np.round(q, 3))
print("q - Q_MIN", np.round(q - panda_spec.Q_MIN, 4))
print("Q_MAX - q", np.round(panda_spec.Q_MAX - q, 4))
print("tau", np.round(tau, 2), "limits", panda_spec.TORQUE_LIMITS, "ms with a joint at its torque limit", saturated_ms)
print("fault", repr(ctrl.fault))
