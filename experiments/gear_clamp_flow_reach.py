"""gear_clamp: how far can the explored flow bend the landscape? (issue 31, item 2, step 3)

The flow of config/gear_clamp.yaml (n_flow 1, identity init, nets seeing (x - x_ref) / flow_input_scale,
explored along ``param_flow_dim`` fixed random directions of the s/t output layers). What the task needs
(experiments/gear_clamp_handflow.py): a translation t_z(x) = -lift(x) of phi's z row, lift about LIFT over
x in [0.56, 0.66] m, about 0 near the shaft (|x - 0.5| < 3 cm) and at the starts (x >= 0.68 m).

Prints, over the approach line (y = 0, z = 0.12 m, x from the shaft to the start):
  - the lift max |dz| of phi minus the identity for one unit (and one initial std) along each explored direction;
  - the best least-squares fit of the needed lift inside the explored subspace and inside all the s/t
    output-layer weights (normalised units): the coefficient norm it takes and the fit's error;
  - whether those subspace fits, with the S, D of experiments/gear_clamp_handflow.py, insert (10 held-out starts);
  - with run folders given, the lift the learned flow mean reached (checkpoint.pt).

    python experiments/gear_clamp_flow_reach.py [RUN_DIR ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from learner_node.config import TrainConfig
from learner_node.flow import RealNVPFlow, rescale_flow_weights
from learner_node.trainer import Trainer

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_clamp.yaml"
EVAL_EPISODES = 10
LIFT = 0.20  # m, as experiments/gear_clamp_handflow.py (whose fit of this shape inserts 6/10)


def needed_lift(xs: np.ndarray) -> np.ndarray:
    """The lift of experiments/gear_clamp_handflow.py: 0 near the shaft and at the starts, LIFT over the clamp."""
    up = 1.0 / (1.0 + np.exp(-(xs - 0.55) / 0.006))
    down = 1.0 / (1.0 + np.exp(-(xs - 0.668) / 0.005))
    return LIFT * up * (1.0 - down)


def lift_of(arch, weights: np.ndarray, pts: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """z component of (phi(x) - phi(x_ref)) - (x - x_ref), negated (a positive value lifts the path)."""
    flow = RealNVPFlow(arch, weights)
    with torch.no_grad():
        phi = flow(torch.as_tensor(pts)).numpy()
        phi_ref = flow(torch.as_tensor(x_ref[None])).numpy()[0]
    return -((phi - phi_ref) - (pts - x_ref))[:, 2]


def main() -> None:
    cfg = TrainConfig.from_sources(CONFIG)
    trainer = Trainer(cfg)
    ex, pol = trainer.explorer, trainer.policy
    x_ref = pol.x_ref.numpy()
    xs = np.linspace(0.50, 0.75, 126)
    pts = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 0.12)], 1)
    need = needed_lift(xs)
    print(f"flow: n_flow {cfg.n_flow}, n_hidden {cfg.n_hidden}, input scale {cfg.flow_input_scale} m, "
          f"{ex.n_flow} explored directions, initial std {cfg.param_sigma_flow}; needed lift {LIFT * 1e3:.0f} mm "
          f"over the clamp")
    base = np.zeros(ex.n_flow)
    lifts = []
    for k in range(ex.n_flow):
        e = base.copy()
        e[k] = 1.0
        lifts.append(lift_of(pol.arch, ex.flow_weights(e), pts, x_ref))
    lifts = np.array(lifts)  # (k, n), nearly linear in the coefficient
    unit = np.abs(lifts).max(1)
    print("one unit along each direction, max lift over the line (mm):", np.round(unit * 1e3, 1).tolist())
    print(f"one initial std ({cfg.param_sigma_flow}) along all {ex.n_flow} at once (rms draw): "
          f"~{cfg.param_sigma_flow * np.sqrt((lifts ** 2).sum(0)).max() * 1e3:.1f} mm")
    # best fits of the needed lift (linear model from the unit responses), ridge-regularised so that the
    # coefficients cannot cancel each other: for each size of the coefficient vector, the fit's error
    mask = ex._flow_mask
    n_out = int(mask.sum())
    full = np.zeros((n_out, len(xs)))
    flat0 = ex.flow_base.numpy().copy()
    for j in range(n_out):
        w = flat0.copy()
        w[np.flatnonzero(mask)[j]] += 1.0
        full[j] = lift_of(pol.arch, rescale_flow_weights(pol.arch, w, x_ref, cfg.flow_input_scale), pts, x_ref)
    over = (xs > 0.57) & (xs < 0.65)
    near = xs < 0.53
    for name, resp in ((f"the {ex.n_flow} explored directions", lifts), (f"all {n_out} output weights", full)):
        print(f"best fit in {name} (coefficient norm in normalised units: error, lift over the clamp, "
              f"|lift| within 3 cm of the shaft):")
        for lam in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6):
            coef = np.linalg.solve(resp @ resp.T + lam * np.eye(len(resp)), resp @ need)
            fit = resp.T @ coef
            print(f"   norm {np.linalg.norm(coef):8.2f}: max error {np.abs(fit - need).max() * 1e3:5.0f} mm, "
                  f"over the clamp {fit[over].min() * 1e3:4.0f}-{fit[over].max() * 1e3:4.0f} mm, "
                  f"near the shaft {np.abs(fit[near]).max() * 1e3:4.0f} mm")
    # does a landscape inside the explored subspace insert? the subspace fits, with the hand-built flow's
    # S, D, deterministic on the first held-out starts
    from learner_node.trainer import EVAL_SEED_BASE, make_evaluator
    with torch.no_grad():
        pol.ln_s.copy_(torch.log(torch.as_tensor([400.0, 400.0, 135.0], dtype=pol.ln_s.dtype)))
        pol.ln_d.copy_(torch.log(torch.as_tensor([40.0, 40.0, 100.0], dtype=pol.ln_d.dtype)))
    for lam in (1e-2, 1e-4, 1e-6):
        coef = np.linalg.solve(lifts @ lifts.T + lam * np.eye(len(lifts)), lifts @ need)
        pol.flow.load_flat(ex.flow_weights(coef))
        pol.sync_gains()
        ev = make_evaluator(pol)
        recs = [trainer.runner.run_episode(ev, None, EVAL_SEED_BASE + k, None) for k in range(EVAL_EPISODES)]
        over_clamp = sum(r.x[:, 0].min() < 0.57 for r in recs)
        print(f"subspace flow of norm {np.linalg.norm(coef):.1f} with S = diag(400, 400, 135), D = diag(40, 40, 100): "
              f"{sum(r.final_success for r in recs)}/{len(recs)} inserted, {over_clamp} over the clamp, "
              f"highest TCP z {max(r.x[:, 2].max() for r in recs):.3f} m")
    for run in sys.argv[1:]:
        ck = torch.load(Path(run) / "checkpoint.pt", weights_only=False)
        weights = np.concatenate([t.reshape(-1).numpy() for k, t in ck["policy"].items() if k.startswith("flow.")])
        mu = ck["explorer"]["flow_mu"].numpy()
        sig = float(np.exp(ck["explorer"]["log_sigma_flow"].numpy()[0]))
        lift = lift_of(pol.arch, weights, pts, x_ref)
        on = lift[over] * 1e3
        print(f"{run}: iteration {ck['iteration']}, flow mean's coefficient norm {np.linalg.norm(mu):.3f}, "
              f"std now {sig:.4f}; lift over the line: max {np.abs(lift).max() * 1e3:.1f} mm, over the clamp "
              f"{on.min():.1f} to {on.max():.1f} mm")


if __name__ == "__main__":
    main()
