"""How close to the edge of success a learned gear controller sits: from a run folder (config.json and
checkpoint.pt of ``train --out``), run its mean controller and mirrored parameter draws around it at
several exploration stds, all from the run's own start (a ``start: fixed`` run: the same start every
time, as on the robot path), and print the fraction of draws that insert.

If draws 3 % away in ln S, ln D (std 0.03) fail as often as draws 30 % away, the failures of training
rollouts are not the exploration's spread but the mean's margin: it inserts, but a small change of the
gains does not.

    python experiments/gear_edge_probe.py RUN_DIR... [--sigmas own 0.01 0.03 0.1] [--part all|gains|flow]
        [--gains SX SY SZ DX DY DZ] [--draws 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from learner_node.config import TrainConfig
from learner_node.trainer import Trainer, make_evaluator


def probe(run_dir: Path, sigmas: list[float | None], draws: int, seed: int = 0, gains: tuple | None = None,
          part: str = "all") -> dict:
    """The mean's outcome and, per std, the success rate of ``draws`` mirrored draws (one std for every
    explored coordinate; None: the run's own stds at its checkpoint), of ``part`` (all; gains: S and D
    only; flow: the flow's subspace only), from the run's start. ``gains`` (S diagonal, D
    diagonal): replace the learned ones (and reset the flow to the identity) to probe a hand-picked
    controller in the run's situation."""
    cfg = TrainConfig(**json.loads((run_dir / "config.json").read_text()))
    trainer = Trainer(cfg)
    trainer.load_checkpoint(run_dir / "checkpoint.pt")
    if gains is not None:
        fresh = Trainer(cfg)  # the prior's flow (the identity) and exploration, with these gains
        with torch.no_grad():
            fresh.policy.ln_s.copy_(torch.log(torch.tensor(gains[0], dtype=torch.float64)))
            fresh.policy.ln_d.copy_(torch.log(torch.tensor(gains[1], dtype=torch.float64)))
        fresh.policy.sync_gains()
        trainer = fresh
    runner, explorer = trainer.runner, trainer.explorer
    if explorer is None:
        raise SystemExit(f"{run_dir}: not a parameter-exploration run")
    start = None if cfg.start == "fixed" else 0
    mean = runner.run_episode(make_evaluator(trainer.policy), None, start, None)
    out = {"run": str(run_dir), "iteration": trainer.iteration, "gains_given": gains is not None,
           "part": part, "start": cfg.start,
           "stiffness": torch.exp(trainer.policy.ln_s).tolist(), "damping": torch.exp(trainer.policy.ln_d).tolist(),
           "mean_success": bool(mean.final_success), "mean_max_depth_mm": float(1000 * mean.depth.max()),
           "per_sigma": []}
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        mu, own = explorer.mean().numpy(), explorer.sigma().numpy()
    for sigma in sigmas:
        half = rng.standard_normal((draws // 2, explorer.dim))
        eps = np.concatenate([half, -half])
        if part == "gains":
            eps[:, explorer.n_gain:] = 0.0
        elif part == "flow":
            eps[:, :explorer.n_gain] = 0.0
        theta = mu + (own if sigma is None else sigma) * eps
        recs = [runner.run_episode(_evaluator(explorer, th), None, start, None) for th in theta]
        out["per_sigma"].append({"sigma": "own" if sigma is None else sigma, "draws": len(recs),
                                 "own_sigma_gains": float(own[:explorer.n_gain].mean()) if explorer.n_gain else None,
                                 "own_sigma_flow": float(own[explorer.n_gain:].mean()) if explorer.n_flow else None,
                                 "success_rate": float(np.mean([r.final_success for r in recs]))})
    return out


def _evaluator(explorer, theta: np.ndarray):
    from nf_controller_node.flow_eval import FlowEvaluator
    return FlowEvaluator(explorer.params_for(theta))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (config.json, checkpoint.pt)")
    ap.add_argument("--sigmas", nargs="+", default=["0.01", "0.03", "0.1", "0.3"],
                    help="stds of the draws; 'own': the run's own stds at its checkpoint")
    ap.add_argument("--draws", type=int, default=20, help="draws per std (mirrored pairs)")
    ap.add_argument("--gains", type=float, nargs=6, metavar=("SX", "SY", "SZ", "DX", "DY", "DZ"),
                    help="probe these diagonal gains (identity flow) in each run's situation instead of its own")
    ap.add_argument("--part", choices=("all", "gains", "flow"), default="all",
                    help="what the draws change: everything explored, S and D only, or the flow only")
    ap.add_argument("--json", type=Path, help="write the results here too")
    args = ap.parse_args(argv)
    gains = (tuple(args.gains[:3]), tuple(args.gains[3:])) if args.gains else None
    sigmas = [None if s == "own" else float(s) for s in args.sigmas]
    results = []
    for run in args.runs:
        r = probe(run, sigmas, args.draws, gains=gains, part=args.part)
        results.append(r)
        sd = " ".join(f"{v:.0f}" for v in r["stiffness"]) + " / " + " ".join(f"{v:.0f}" for v in r["damping"])
        rates = "  ".join(f"std {p['sigma']}: {p['success_rate']:.2f}" for p in r["per_sigma"])
        print(f"{run} (it. {r['iteration']}, S/D {sd}): mean {'inserts' if r['mean_success'] else 'fails'} "
              f"(depth {r['mean_max_depth_mm']:.1f} mm); draws of {args.part} inserting  {rates}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
