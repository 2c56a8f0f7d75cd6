"""Learner wall time of NF-PPO against MLP-PPO: one PPO update, and one whole training iteration.

Update: a batch of the gear task's shape (15 rollouts x 500 decisions, 3-D task-space state)
updated for 10 epochs in minibatches of 64 with the trainer's optimiser. States, actions and
advantages are synthetic (seeded): the cost of an update depends only on the shapes. Medians
over repeats, each on a fresh policy. Also one forward+backward of ``log_prob`` on a minibatch.

Iteration (the issue's measures, "NF-PPO wall time per training iteration <= 1.2x MLP-PPO and no
slower than stable-baselines3's PPO"): ``Trainer.train_iteration`` on the gear task (config/gear.yaml:
simulated rollouts + update) for NF-PPO and MLP-PPO, and one ``learn`` call of stable-baselines3's
PPO on the same task through ``learner_node.analysis.gym_env`` (one rollout of the same batch, rollouts_per_iter
x decisions per episode, + its update with the config's epochs, minibatch, lr, gamma, lambda, clip),
as an outside reference. One warm-up iteration each, then ``--repeats`` iterations of the three in
turn (interleaved, so load drift on the shared machine hits all alike); medians. stable-baselines3
is a bench-only dependency (requirements/bench.txt): without it that part is skipped and says why.
Skip the whole iteration timing with ``--no-iteration``.

NF policy: n_flow 2, n_hidden 16, GELU; MLP policy: 2 x 64 tanh; both float64, one torch thread.
stable-baselines3: its MlpPolicy (2 x 64 tanh actor, 2 x 64 critic, float32), same torch threads.
Writes ``bench/results/learner_update.json`` and prints it.

    python bench/bench_learner.py [--quick] [--no-iteration]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
for pkg in ("nf_core", "nf_controller_node", "learner_node", "sim_bridge_node"):
    if str(ROOT / pkg) not in sys.path:
        sys.path.insert(0, str(ROOT / pkg))

from learner_node.config import MLP_ACTIVATION, MLP_HIDDEN, TrainConfig  # noqa: E402
from learner_node.mlp_policy import MLPPolicy  # noqa: E402
from learner_node.policy import NFPolicy  # noqa: E402
from learner_node.ppo import PPOBatch, PPOSettings, make_optimizer, ppo_update  # noqa: E402
from nf_core.flow_spec import FlowArchitecture  # noqa: E402

DIM = 3
N_FLOW, N_HIDDEN = 2, 16
X_REF = np.array([0.5, 0.0, 0.3])
TARGET_RATIO = 1.2  # NF-PPO iteration <= 1.2x MLP-PPO's
TARGET_SB3_RATIO = 1.0  # and no slower than stable-baselines3's PPO


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


def gear_config(kind: str, rollouts: int) -> TrainConfig:
    """The gear task's ``TrainConfig`` (config/gear.yaml) for policy ``kind`` with ``rollouts`` per iteration."""
    overrides: dict[str, Any] = {"policy": kind, "iterations": 1, "eval_episodes": 0, "rollouts_per_iter": rollouts}
    if kind == "nf":
        overrides.update(n_flow=N_FLOW, n_hidden=N_HIDDEN)
    return TrainConfig.from_sources(ROOT / "config" / "gear.yaml", overrides)


def trainer_iteration(kind: str, rollouts: int) -> Callable[[], dict[str, float]]:
    """One ``Trainer.train_iteration`` per call (``nf`` or ``mlp``): rollout, update and wall seconds."""
    from learner_node.trainer import Trainer

    trainer = Trainer(gear_config(kind, rollouts))

    def run() -> dict[str, float]:
        row = trainer.train_iteration()
        return {k: row[k] for k in ("rollout_seconds", "update_seconds", "wall_seconds")}

    return run


def sb3_missing() -> str | None:
    """Why stable-baselines3's PPO cannot run here, or None if it can."""
    try:
        import gymnasium  # noqa: F401
        import stable_baselines3  # noqa: F401
    except ImportError as exc:
        return f"stable-baselines3 not importable ({exc}); pip install -r requirements/bench.txt (make bench does)"
    return None


def sb3_iteration(rollouts: int) -> tuple[Callable[[], dict[str, float]], dict[str, Any]]:
    """One stable-baselines3 PPO iteration per call on the gear task, and the settings used.

    ``n_steps`` = rollouts x decisions per episode, so one ``learn`` call is exactly one rollout of
    our batch size plus one update; the PPO settings come from the same config as the trainer's.
    """
    import stable_baselines3
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    from learner_node.analysis.gym_env import InsertionGymEnv

    cfg = gear_config("mlp", rollouts)
    n_steps = rollouts * cfg.decisions_per_episode
    settings = {
        "n_steps": n_steps, "batch_size": cfg.minibatch_size, "n_epochs": cfg.update_epochs,
        "learning_rate": cfg.learning_rate, "gamma": cfg.gamma, "gae_lambda": cfg.gae_lambda,
        "clip_range": cfg.clip_coef, "normalize_advantage": True, "ent_coef": 0.0,
        "vf_coef": 0.5, "max_grad_norm": math.inf, "target_kl": None,
    }
    act = {"tanh": torch.nn.Tanh, "gelu": torch.nn.GELU}[MLP_ACTIVATION]
    policy_kwargs = {"net_arch": {"pi": [MLP_HIDDEN] * 2, "vf": [MLP_HIDDEN] * 2}, "activation_fn": act,
                     "log_std_init": math.log(cfg.sigma_init)}
    with warnings.catch_warnings():  # n_steps not a multiple of the minibatch: a short last one, as ours
        warnings.filterwarnings("ignore", message=".*mini-batch size.*")
        model = PPO("MlpPolicy", InsertionGymEnv(cfg), policy_kwargs=policy_kwargs, seed=cfg.seed, device="cpu",
                    verbose=0, **settings)

    class RolloutClock(BaseCallback):
        """Seconds of the last rollout (collection only; the update follows it inside ``learn``)."""

        seconds = 0.0

        def _on_rollout_start(self) -> None:
            self._t0 = time.perf_counter()

        def _on_rollout_end(self) -> None:
            self.seconds = time.perf_counter() - self._t0

        def _on_step(self) -> bool:
            return True

    clock = RolloutClock()

    def run() -> dict[str, float]:
        t0 = time.perf_counter()
        model.learn(total_timesteps=n_steps, callback=clock, reset_num_timesteps=False)
        wall = time.perf_counter() - t0
        return {"rollout_seconds": clock.seconds, "update_seconds": wall - clock.seconds, "wall_seconds": wall}

    info = {"version": stable_baselines3.__version__, "policy": "MlpPolicy", "dtype": "float32",
            "net_arch": policy_kwargs["net_arch"], "activation": cfg.mlp_activation, "n_envs": 1,
            "env": "learner_node.analysis.gym_env.InsertionGymEnv (gear, force held per decision period)",
            **settings, "max_grad_norm": settings["max_grad_norm"] if cfg.max_grad_norm > 0 else None,
            "torch_threads": torch.get_num_threads()}
    return run, info


def time_iterations(rollouts: int, repeats: int) -> dict[str, Any]:
    """Warm-up, then ``repeats`` interleaved iterations of NF-PPO, MLP-PPO and (if available) SB3 PPO."""
    runs: dict[str, Callable[[], dict[str, float]]] = {k: trainer_iteration(k, rollouts) for k in ("nf", "mlp")}
    out: dict[str, Any] = {"warmup_iterations": 1, "repeats": repeats}
    missing = sb3_missing()
    if missing is None:
        runs["sb3"], sb3_info = sb3_iteration(rollouts)
    else:
        print(f"SKIPPED stable-baselines3 PPO: {missing}", file=sys.stderr, flush=True)
        out["sb3"] = {"skipped": missing}
    for run in runs.values():  # first iteration: numba caches, torch kernels, SB3's env reset
        run()
    rows: dict[str, list[dict[str, float]]] = {k: [] for k in runs}
    for _ in range(repeats):
        for kind, run in runs.items():
            rows[kind].append(run())
    for kind, rs in rows.items():
        out[kind] = {f"{key}_median": statistics.median(r[key] for r in rs) for key in rs[0]}
        out[kind]["wall_seconds"] = [r["wall_seconds"] for r in rs]
    if missing is None:
        out["sb3"]["settings"] = sb3_info
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmark, write bench/results/learner_update.json, print and return the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 rollouts instead of 15 (a smoke run)")
    parser.add_argument("--repeats", type=int, default=3, help="timed updates and (after a warm-up) iterations")
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
        it = time_iterations(rollouts, args.repeats)
        results["iteration"] = it
        nf_s, mlp_s = it["nf"]["wall_seconds_median"], it["mlp"]["wall_seconds_median"]
        s = results["summary"]
        s.update(iteration_nf_s=round(nf_s, 3), iteration_mlp_s=round(mlp_s, 3),
                 iteration_nf_over_mlp=round(nf_s / mlp_s, 3), target_iteration_max=TARGET_RATIO,
                 meets_target=nf_s / mlp_s <= TARGET_RATIO)
        if "skipped" in it["sb3"]:
            s["sb3_skipped"] = it["sb3"]["skipped"]
        else:
            sb3_s = it["sb3"]["wall_seconds_median"]
            s.update(iteration_sb3_s=round(sb3_s, 3), iteration_nf_over_sb3=round(nf_s / sb3_s, 3),
                     target_nf_over_sb3_max=TARGET_SB3_RATIO, meets_sb3_target=nf_s / sb3_s <= TARGET_SB3_RATIO)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
