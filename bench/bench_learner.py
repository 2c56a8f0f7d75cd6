"""Learner wall time of NF-PPO against MLP-PPO: one PPO update, and one whole training iteration.

Update: a batch of the gear task's shape (15 rollouts x 500 decisions, 3-D task-space state)
updated for 10 epochs in minibatches of 64 with the trainer's optimiser. States, actions and
advantages are synthetic (seeded): the cost of an update depends only on the shapes. Medians
over repeats, each on a fresh policy. Also one forward+backward of ``log_prob`` on a minibatch.

Iteration (the issue's measure, "NF-PPO wall time per training iteration <= 1.2x MLP-PPO"):
one ``Trainer.train_iteration`` on the gear task (simulated rollouts + update), once per
policy; skip it with ``--no-iteration``.

NF policy: n_flow 2, n_hidden 16, GELU; MLP policy: 2 x 64 tanh; both float64, one torch thread.
Writes ``bench/results/learner_update.json`` and prints it.

    python bench/bench_learner.py [--quick] [--no-iteration]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
for pkg in ("nf_controller_node", "learner_node", "sim_bridge_node"):
    if str(ROOT / pkg) not in sys.path:
        sys.path.insert(0, str(ROOT / pkg))

from learner_node.mlp_policy import MLPPolicy  # noqa: E402
from learner_node.policy import NFPolicy  # noqa: E402
from learner_node.ppo import PPOBatch, PPOSettings, make_optimizer, ppo_update  # noqa: E402
from nf_controller_node.flow_spec import FlowArchitecture  # noqa: E402

DIM = 3
N_FLOW, N_HIDDEN = 2, 16
X_REF = np.array([0.5, 0.0, 0.3])
TARGET_RATIO = 1.2


def make_policy(kind: str) -> NFPolicy | MLPPolicy:
    """A freshly initialised policy of the gear task's shape (``nf`` or ``mlp``)."""
    if kind == "nf":
        arch = FlowArchitecture(dim=DIM, n_flow=N_FLOW, n_hidden=N_HIDDEN, activation="gelu")
        return NFPolicy(arch, stiffness=4.0 * np.eye(DIM), damping=np.eye(DIM), x_ref=X_REF, sigma_init=5.0)
    return MLPPolicy(DIM, 64, "tanh", x_ref=X_REF, sigma_init=5.0)


def make_batch(policy: NFPolicy | MLPPolicy, n: int, seed: int = 0) -> PPOBatch:
    """A synthetic batch of ``n`` decisions: states near the goal, actions drawn from the policy itself."""
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(X_REF + rng.normal(scale=0.05, size=(n, DIM)))
    xdot = torch.from_numpy(rng.normal(scale=0.05, size=(n, DIM)))
    with torch.no_grad():
        action = policy.mean_force(x, xdot) + 5.0 * torch.from_numpy(rng.normal(size=(n, DIM)))
        old_lp = policy.log_prob(x, xdot, action)
    adv = rng.normal(size=n)
    adv = torch.from_numpy((adv - adv.mean()) / adv.std())
    return PPOBatch(x=x, xdot=xdot, action=action, old_log_prob=old_lp, advantages=adv,
                    returns=torch.zeros(n, dtype=torch.float64))


def time_update(kind: str, n: int, settings: PPOSettings, repeats: int) -> dict[str, Any]:
    """Median wall time of ``ppo_update`` over fresh policies, and of one minibatch log_prob fwd+bwd."""
    warm = make_policy(kind)  # first use compiles the kernels or loads numba's cache: not timed
    ppo_update(warm, make_optimizer(list(warm.parameters()), 2.5e-4), make_batch(warm, settings.minibatch_size),
               PPOSettings(update_epochs=1, minibatch_size=settings.minibatch_size), np.random.default_rng(0))
    times = []
    for r in range(repeats):
        policy = make_policy(kind)
        batch = make_batch(policy, n, seed=r)
        opt = make_optimizer(list(policy.parameters()), 2.5e-4)  # as the trainer
        t0 = time.perf_counter()
        ppo_update(policy, opt, batch, settings, np.random.default_rng(r))
        times.append(time.perf_counter() - t0)
    policy = make_policy(kind)
    batch = make_batch(policy, settings.minibatch_size, seed=99)
    step_times = []
    for _ in range(7):
        t0 = time.perf_counter()
        for _ in range(50):
            policy.zero_grad()
            policy.log_prob(batch.x, batch.xdot, batch.action).sum().backward()
        step_times.append((time.perf_counter() - t0) / 50)
    return {
        "update_seconds_median": statistics.median(times),
        "update_seconds": times,
        "log_prob_fwd_bwd_us_median": 1e6 * statistics.median(step_times),
    }


def time_iteration(kind: str, rollouts: int) -> dict[str, float]:
    """Seconds of one ``Trainer.train_iteration`` on the gear task: rollouts, update, wall."""
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer

    overrides: dict[str, Any] = {"policy": kind, "iterations": 1, "eval_episodes": 0, "rollouts_per_iter": rollouts}
    if kind == "nf":
        overrides.update(n_flow=N_FLOW, n_hidden=N_HIDDEN)
    trainer = Trainer(TrainConfig.from_sources(ROOT / "config" / "gear.yaml", overrides))
    row = trainer.train_iteration()
    return {k: row[k] for k in ("rollout_seconds", "update_seconds", "wall_seconds")}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmark, write bench/results/learner_update.json, print and return the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 rollouts instead of 15 (a smoke run)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-iteration", action="store_true", help="skip the training-iteration timing")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "learner_update.json"))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # as the trainer: small tensors, shared 2-core machine
    rollouts, decisions = (3 if args.quick else 15), 500
    n = rollouts * decisions
    settings = PPOSettings(update_epochs=10, minibatch_size=64)
    nf = time_update("nf", n, settings, args.repeats)
    mlp = time_update("mlp", n, settings, args.repeats)
    ratio = nf["update_seconds_median"] / mlp["update_seconds_median"]
    results: dict[str, Any] = {
        "what": "NF-PPO vs MLP-PPO learner wall time, gear-task shape (dim 3); update medians over repeats",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
                    "torch_threads": torch.get_num_threads(), "load_avg_1min": os.getloadavg()[0]},
        "batch": {"rollouts": rollouts, "decisions_per_rollout": decisions, "decisions": n,
                  "update_epochs": settings.update_epochs, "minibatch_size": settings.minibatch_size},
        "repeats": args.repeats,
        "nf": {"n_flow": N_FLOW, "n_hidden": N_HIDDEN, "activation": "gelu", "dtype": "float64", **nf},
        "mlp": {"hidden": [64, 64], "activation": "tanh", "dtype": "float64", **mlp},
        "summary": {"nf_update_s": round(nf["update_seconds_median"], 3),
                    "mlp_update_s": round(mlp["update_seconds_median"], 3),
                    "update_nf_over_mlp": round(ratio, 3)},
    }
    if not args.no_iteration:
        it = {kind: time_iteration(kind, rollouts) for kind in ("nf", "mlp")}
        wall_ratio = it["nf"]["wall_seconds"] / it["mlp"]["wall_seconds"]
        results["iteration"] = it
        results["summary"].update(iteration_nf_over_mlp=round(wall_ratio, 3), target_iteration_max=TARGET_RATIO,
                                  meets_target=wall_ratio <= TARGET_RATIO)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
