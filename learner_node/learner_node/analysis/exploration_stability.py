"""Stable exploration, measured: does an exploration rollout's Lyapunov function rise in free space?

For an NF policy and an exploration scheme, run exploration rollouts on the Panda in the free scene
(no fixture, no contact: the closed loop of the controller alone) and record, every millisecond, the
Lyapunov function of the controller that runs::

    V = 1/2 dphi^T S dphi + k_rot/2 (3 - tr(R_ref^T R)) + 1/2 dq^T M(q) dq   (FlowController.lyapunov)

Schemes: ``none`` (the deterministic controller: the integration-error baseline), ``action`` (Gaussian
force noise of std sigma held ``hold`` s, added to the policy's force: V is the policy's), ``params``
(each rollout a deterministic controller with parameters drawn as the trainer's ``ParamExploration``
draws them: V is that rollout's own controller's). Per rollout:

- ``rise``: the largest increase of V over its running minimum, max_t [V(t) - min_{s<=t} V(s)], J; the
  rollout "rises" if this exceeds ``tolerance`` (integration and sampling error: see ``none``);
- ``work``: the work the exploration does on the arm, sum of f_expl . xdot dt, J, with f_expl the
  noise (action) or the drawn controller's force minus the policy's (params), both at the TCP;
- ``gain``: V(end) - V(start), J (passivity: <= 0 without an external force);
- ``limited_ms``: milliseconds in which a joint torque hit its limit or the torque rate limit: the
  applied torque is then not the stable law's, and the proof does not cover those steps.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.torque_law import CLAMPED, RATE_LIMITED, TorqueLawConfig
from nf_core import panda_spec
from sim_bridge_node.env import InsertionEnv

from ..config import PHYSICS_DT, TrainConfig
from ..param_explore import ParamExploration
from ..policy import NFPolicy
from ..trainer import EVAL_SEED_BASE, build_policy

SCHEMES = ("none", "action", "params")
DEFAULT_TOLERANCE = 1e-6  # J: the controller's LyapunovMonitor's per-step integration tolerance


@dataclass
class RolloutEnergy:
    """Energy record of one free-space exploration rollout."""

    start_seed: int
    rise: float  # J, max_t V(t) - min_{s<=t} V(s)
    work: float  # J, work of the exploration force on the TCP
    gain: float  # J, V(end) - V(start)
    v0: float  # J, V at the start
    fault: str
    limited_ms: int = 0  # milliseconds whose torque hit the torque or rate limit (the law is then not exact)
    clamped_ms: int = 0  # ... of those, milliseconds with a joint torque at its limit
    rate_limited_ms: int = 0  # ... and with a torque step cut to the rate limit
    v_max: float = 0.0  # J, the largest V of the rollout


def free_space_rollout(
    env: InsertionEnv,
    ctrl: FlowController,
    nominal: FlowEvaluator,
    seconds: float,
    start_seed: int,
    sigma: float = 0.0,
    hold: float = 0.01,
    rng: np.random.Generator | None = None,
) -> RolloutEnergy:
    """One rollout from ``start_seed`` with ``ctrl``'s evaluator (plus held noise of std ``sigma`` N);
    exploration force measured against ``nominal`` (the policy's own evaluator)."""
    env.reset(seed=start_seed)
    ctrl.reset_rate_limit()
    ctrl.clear_fault()
    steps = round(seconds / PHYSICS_DT)
    per_hold = max(1, round(hold / PHYSICS_DT))
    eps = np.zeros(3)
    u_nom = np.zeros(3)
    noisy = sigma > 0.0
    v = ctrl.lyapunov(env.q, env.dq)
    v0 = v_min = v
    rise = work = 0.0
    limited = clamped = rated = 0
    v_max = v
    for k in range(steps):
        if noisy and k % per_hold == 0:
            eps = sigma * rng.standard_normal(3)
        tau = ctrl.step(env.q, env.dq, eps if noisy else None)
        flags = ctrl.flags
        limited += int(bool(flags & (CLAMPED | RATE_LIMITED)))
        clamped += int(bool(flags & CLAMPED))
        rated += int(bool(flags & RATE_LIMITED))
        if noisy:
            f = eps
        else:
            nominal.force(ctrl.arm.x, ctrl.xdot, u_nom)
            f = ctrl.u - u_nom
        work += float(f @ ctrl.xdot) * PHYSICS_DT
        env.step(tau)
        v = ctrl.lyapunov(env.q, env.dq)
        v_min = min(v_min, v)
        v_max = max(v_max, v)
        rise = max(rise, v - v_min)
    return RolloutEnergy(start_seed, rise, work, v - v0, v0, ctrl.fault, limited, clamped, rated, v_max)


def measure(
    policy: NFPolicy,
    scheme: str,
    rollouts: int,
    seconds: float,
    *,
    sigma: float = 1.0,
    hold: float = 0.01,
    explorer: ParamExploration | None = None,
    seed: int = 0,
    force_bound: float = 0.0,
) -> list[RolloutEnergy]:
    """``rollouts`` free-space rollouts of ``scheme`` from held-out starts (params: mirrored draws of
    ``explorer``, as in training)."""
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    env = InsertionEnv("free")
    arm = ArmModel(part=panda_spec.GEAR_PART)  # the free scene's hand holds the gear
    nominal = FlowEvaluator(policy.to_params())
    ctrl = FlowController(arm, nominal, TorqueLawConfig(potential_force_bound=force_bound))  # bounds every draw too
    rng = np.random.default_rng(seed)
    draws: np.ndarray | None = None
    if scheme == "params":
        if explorer is None:
            raise ValueError("scheme params needs an explorer")
        draws, _ = explorer.sample(rollouts, rng)
    out = []
    for k in range(rollouts):
        start = EVAL_SEED_BASE + (k // 2 if scheme == "params" else k)  # mirrored pairs share a start
        if draws is not None:
            ctrl.set_evaluator(FlowEvaluator(explorer.params_for(draws[k])))
        out.append(free_space_rollout(env, ctrl, nominal, seconds, start,
                                      sigma=sigma if scheme == "action" else 0.0, hold=hold, rng=rng))
        ctrl.set_evaluator(nominal)
    return out


def summarize(records: list[RolloutEnergy], tolerance: float = DEFAULT_TOLERANCE) -> dict[str, Any]:
    """Fraction of rollouts whose V rises beyond ``tolerance``; work and V gain statistics."""
    rise = np.array([r.rise for r in records])
    limited = np.array([r.limited_ms > 0 for r in records])
    work = np.array([r.work for r in records])
    gain = np.array([r.gain for r in records])
    return {
        "rollouts": len(records),
        "tolerance_J": tolerance,
        "rising_fraction": float(np.mean(rise > tolerance)),
        "limited_fraction": float(np.mean(limited)),
        "rising_unlimited_fraction": float(np.mean((rise > tolerance) & ~limited)),
        "rise_max_J": float(rise.max()),
        "rise_median_J": float(np.median(rise)),
        "work_mean_J": float(work.mean()),
        "work_max_J": float(work.max()),
        "gain_max_J": float(gain.max()),
        "faults": sum(bool(r.fault) for r in records),
        # the rising rollouts: which limit they hit, and how the rise compares with where V started
        "rising_clamped_fraction": float(np.mean((rise > tolerance) & np.array([r.clamped_ms > 0 for r in records]))),
        "rising_rate_only_fraction": float(np.mean((rise > tolerance) & np.array(
            [r.clamped_ms == 0 and r.rate_limited_ms > 0 for r in records]))),
        "rise_over_v0_max": float(max((r.rise / r.v0 for r in records if r.v0 > 0), default=0.0)),
        "per_rollout": [{"start_seed": r.start_seed, "v0_J": r.v0, "v_max_J": r.v_max, "rise_J": r.rise,
                         "gain_J": r.gain, "clamped_ms": r.clamped_ms, "rate_limited_ms": r.rate_limited_ms}
                        for r in records],
    }


def load_policy(cfg: TrainConfig, checkpoint: Path | None) -> tuple[NFPolicy, ParamExploration | None]:
    """The run's NF policy (iteration 0 without a checkpoint) and, for exploration=params, its explorer."""
    env = InsertionEnv(cfg.task)
    policy = build_policy(cfg, env.goal_position.copy())
    if not isinstance(policy, NFPolicy):
        raise ValueError("the stability measurement is for the NF policy (policy: nf)")
    explorer = None
    if cfg.exploration == "params":
        explorer = ParamExploration(policy, cfg.param_sigma_gains, cfg.param_sigma_flow, cfg.flow_input_scale,
                                    cfg.param_flow, cfg.param_flow_dim, cfg.seed)
    if checkpoint is not None:
        state = torch.load(checkpoint, weights_only=True)
        policy.load_state_dict(state["policy"])
        if explorer is not None and state.get("explorer") is not None:
            explorer.load_state_dict(state["explorer"])
    return policy, explorer


def main(argv: list[str] | None = None) -> int:
    """CLI: one table row (JSON) per scheme for a config or a run's checkpoint."""
    ap = argparse.ArgumentParser(prog="exploration_stability", description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, required=True, help="task YAML (e.g. config/gear.yaml)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--checkpoint", type=Path, help="a run's checkpoint.pt (default: the untrained policy)")
    ap.add_argument("--schemes", default="none,action,params", help="comma-separated, of none|action|params")
    ap.add_argument("--rollouts", type=int, default=15)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--sigma", type=float, help="action noise std, N (default: the policy's)")
    ap.add_argument("--hold", type=float, help="action noise hold, s (default: decision_period)")
    ap.add_argument("--tolerance", type=float, default=DEFAULT_TOLERANCE, help="J")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args(argv)
    overrides = dict(item.split("=", 1) for item in args.sets)
    cfg = TrainConfig.from_sources(args.config, overrides)
    policy, explorer = load_policy(cfg, args.checkpoint)
    if explorer is None:  # measure parameter exploration around this policy at the config's stds
        if cfg.gains == "fixed":
            cfg = TrainConfig.from_sources(args.config, {**overrides, "gains": "learned"})
            learned, _ = load_policy(cfg, None)
            learned.flow.load_flat(policy.flow.to_flat())
            policy = learned
        explorer = ParamExploration(policy, cfg.param_sigma_gains, cfg.param_sigma_flow, cfg.flow_input_scale,
                                    cfg.param_flow, cfg.param_flow_dim, cfg.seed)
    sigma = float(policy.std().detach().mean()) if args.sigma is None else args.sigma
    hold = cfg.decision_period if args.hold is None else args.hold
    rows = []
    for scheme in args.schemes.split(","):
        recs = measure(policy, scheme, args.rollouts, args.seconds, sigma=sigma, hold=hold, explorer=explorer,
                       force_bound=cfg.potential_force_bound)
        row = {"scheme": scheme, "potential_force_bound_N": cfg.potential_force_bound,
               "sigma_N": sigma if scheme == "action" else None,
               "hold_s": hold if scheme == "action" else None,
               "param_sigma_gains": float(torch.exp(explorer.log_sigma_gains.detach()).mean())
               if scheme == "params" else None,
               **summarize(recs, args.tolerance)}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "per_rollout"}), flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
