"""Where the robot path's first iterations go: the gear from a fixed start straight above the shaft,
with joint friction, for a grid of diagonal gains (identity flow), one deterministic episode each.

The robot path (franky-sim, docs/hardware.md) starts every episode at the same TCP 20 cm above the
goal, and its arm has Coulomb joint friction. This reproduces that situation in our MuJoCo scene
(``start: fixed``, TCP (0.5, 0, 0.29), 22 cm above the goal; ``friction_coulomb`` one value on every
joint) and prints, per friction and gains: the lateral offset from the shaft axis at the end (mm), the
deepest insertion (mm, success at 16), the time of success (s) and the episode's return. It shows how
narrow and how friction-dependent the set of gains that insert is, which is what the learner has to
find with a few mirrored draws per iteration.

    python experiments/fixed_start_gains.py [--friction 0 0.3 0.6 1.0] [--bound 0] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from learner_node.config import TrainConfig
from learner_node.rollout import RolloutRunner
from learner_node.trainer import build_policy, make_evaluator

# (S diagonal N/m, D diagonal N s/m): the prior, isotropic stiffer ones, stiff-lateral ones and the mean
# of a learning run (seed 0 of the proxy, iteration 12) that still failed
GAINS = [
    ((300, 300, 300), (40, 40, 40)),
    ((600, 600, 300), (40, 40, 40)),
    ((1000, 300, 300), (40, 40, 40)),
    ((1000, 1000, 300), (40, 40, 40)),
    ((1000, 1000, 300), (80, 80, 40)),
    ((1000, 1000, 300), (40, 40, 10)),
    ((1000, 1000, 1000), (40, 40, 40)),
    ((2000, 2000, 2000), (60, 60, 60)),
    ((1397, 284, 212), (78, 24, 11)),
]


def probe(config: str, friction: float, bound: float, stiffness: tuple, damping: tuple) -> dict:
    """One deterministic episode from the fixed start with these gains, friction and force bound."""
    cfg = TrainConfig.from_sources(config, {"start": "fixed", "friction_coulomb": [friction, friction],
                                            "potential_force_bound": bound})
    runner = RolloutRunner(cfg)
    policy = build_policy(cfg, runner.x_ref)
    with torch.no_grad():
        policy.ln_s.copy_(torch.log(torch.tensor(stiffness, dtype=torch.float64)))
        policy.ln_d.copy_(torch.log(torch.tensor(damping, dtype=torch.float64)))
    policy.sync_gains()
    rec = runner.run_episode(make_evaluator(policy), None, None, None)
    err = rec.x[-1] - runner.x_ref
    hit = np.flatnonzero(rec.success)
    return {"friction": friction, "bound": bound, "stiffness": list(stiffness), "damping": list(damping),
            "lateral_mm": float(1000 * np.linalg.norm(err[:2])), "max_depth_mm": float(1000 * rec.depth.max()),
            "success": bool(rec.final_success), "t_success": float(rec.t[hit[0]]) if hit.size else None,
            "return": rec.episode_return}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="fixed_start_gains", description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/gear_learn.yaml")
    ap.add_argument("--friction", type=float, nargs="+", default=[0.0, 0.3, 0.6, 1.0],
                    help="Coulomb friction on every joint, Nm (one episode set per value)")
    ap.add_argument("--bound", type=float, default=0.0, help="potential_force_bound, N (0: off, the robot path's)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    rows = []
    print(f"{'friction':>8} {'S (N/m)':>18} {'D (N s/m)':>12} {'lateral mm':>10} {'depth mm':>8} {'success at':>10}")
    for friction in args.friction:
        for stiffness, damping in GAINS:
            r = probe(args.config, friction, args.bound, stiffness, damping)
            rows.append(r)
            at = f"{r['t_success']:.2f} s" if r["t_success"] is not None else "-"
            print(f"{friction:8.2f} {stiffness!s:>18} {damping!s:>12} {r['lateral_mm']:10.2f} "
                  f"{r['max_depth_mm']:8.1f} {at:>10}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
