"""gear_clamp: a shaped landscape that does get the gear over the clamp (issue 31, item 2).

Not learned: built by hand inside the architecture of config/gear_clamp.yaml (n_flow 1, n_hidden 16,
identity init). Only the output row of the first coupling layer's t-network that translates z is set
(16 weights and a bias, on the net's fixed random hidden features of x): least squares to a lift of
LIFT over the clamp (x 0.55-0.67 m), 0 near the shaft and at the starts, so that
phi_z(x) = z - lift(x). With S, D = diag(400, 400, 135) N/m, diag(40, 40, 100) N s/m the latent point
moves straight to the goal while the real gear rises over the clamp, comes down behind it on the
shaft's side and is inserted; the same S, D with the identity flow (one quadratic well) stop at the
clamp. Both deterministic, on the training's held-out evaluation starts.

    python experiments/gear_clamp_handflow.py [--episodes 10] [--png docs/results/gear_clamp/landscape.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from learner_node.config import TrainConfig
from learner_node.flow import activation_and_derivative, rescale_flow_weights
from learner_node.trainer import EVAL_SEED_BASE, Trainer, make_evaluator
from nf_core.task_spec import load_task

TASK = load_task("gear_clamp")

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_clamp.yaml"
LIFT = 0.20  # m, plateau of the lift (the fit reaches ~0.17-0.21 m over the clamp)
S_DIAG = [400.0, 400.0, 135.0]  # N/m: lateral as on the plain gear, soft axial (slow latent z)
D_DIAG = [40.0, 40.0, 100.0]  # N s/m: the axial damping holds the latent z while x moves
T_NET = 6  # index of layer 0's t-network among the flow's parameter arrays (W1, b1, W2, b2, W3, b3)


def target_lift(xs: np.ndarray) -> np.ndarray:
    up = 1.0 / (1.0 + np.exp(-(xs - 0.55) / 0.006))  # rises behind the shaft ...
    down = 1.0 / (1.0 + np.exp(-(xs - 0.668) / 0.005))  # ... and falls off before the starts (x >= 0.68)
    return LIFT * up * (1.0 - down)


def build(trainer: Trainer) -> np.ndarray:
    """Set layer 0's t_z output row of ``trainer.policy`` to the fitted lift; returns the fit on a grid."""
    pol = trainer.policy
    W1, b1, W2, b2, W3, b3 = (pol.flow.params[T_NET + k] for k in range(6))
    xs = np.linspace(0.40, 0.85, 400)
    with torch.no_grad():
        h1, _ = activation_and_derivative("gelu", torch.as_tensor(xs[:, None]) @ W1.T + b1, False)
        h2, _ = activation_and_derivative("gelu", h1 @ W2.T + b2, False)
    F = np.hstack([h2.numpy(), np.ones((len(xs), 1))])
    w = np.where(xs < 0.535, 10.0, 1.0)  # insist on no lift near the shaft
    target = -target_lift(xs)  # phi_z = z + t_z(x): a negative translation lifts the real path
    coef = np.linalg.solve((F * w[:, None]).T @ (F * w[:, None]) + 1e-8 * np.eye(F.shape[1]),
                           (F * w[:, None]).T @ (target * w))
    with torch.no_grad():
        W3[1].copy_(torch.as_tensor(coef[:-1]))
        b3[1].copy_(torch.as_tensor(coef[-1]))
    return np.stack([xs, target_lift(xs), -(F @ coef)], 1)


def set_gains(trainer: Trainer) -> None:
    pol = trainer.policy
    with torch.no_grad():
        pol.ln_s.copy_(torch.log(torch.as_tensor(S_DIAG, dtype=pol.ln_s.dtype)))
        pol.ln_d.copy_(torch.log(torch.as_tensor(D_DIAG, dtype=pol.ln_d.dtype)))
    pol.sync_gains()


def evaluate(trainer: Trainer, n: int) -> list:
    ev = make_evaluator(trainer.policy)
    return [trainer.runner.run_episode(ev, None, EVAL_SEED_BASE + k, None) for k in range(n)]


def report(name: str, recs: list) -> None:
    ok = sum(r.final_success for r in recs)
    print(f"{name}: {ok}/{len(recs)} inserted; highest TCP z {max(r.x[:, 2].max() for r in recs):.3f} m; "
          f"final TCP {[np.round(r.x[-1], 3).tolist() for r in recs]}; mean torque "
          f"{np.mean([r.torque_norm for r in recs]):.1f} Nm")


def plot(path: Path, columns: dict, paths: dict) -> None:
    """V on the x-z slice through the shaft axis (y = 0) per policy, the clamp and the shaft drawn, with
    the TCP paths of the evaluation episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle


    xs, zs = np.linspace(0.42, 0.78, 145), np.linspace(0.04, 0.32, 113)
    gx, gz = np.meshgrid(xs, zs)
    pts = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1)
    fig, axes = plt.subplots(1, len(columns), figsize=(6.0 * len(columns), 5.4), squeeze=False)
    vs = {}
    for name, pol in columns.items():
        with torch.no_grad():
            vs[name] = pol.lyapunov_potential(torch.from_numpy(pts)).numpy().reshape(gx.shape)
    vmax = max(float(v.max()) for v in vs.values())
    levels = np.geomspace(1e-4 * vmax, vmax, 25)
    for ax, (name, v) in zip(axes[0], vs.items(), strict=True):
        cs = ax.contourf(gx * 100, gz * 100, np.clip(v, levels[0], None), levels=levels, cmap="viridis",
                         norm=LogNorm())
        ax.contour(gx * 100, gz * 100, np.clip(v, levels[0], None), levels=levels, colors="k", linewidths=0.3,
                   alpha=0.5)
        c0 = TASK.clamp.center_x - TASK.clamp.half_thickness
        ax.add_patch(Rectangle((c0 * 100, 0), 2 * TASK.clamp.half_thickness * 100, TASK.clamp.top * 100,
                               color="0.85", ec="k", label="clamp"))
        ax.add_patch(Rectangle(((TASK.top[0] - TASK.fixture.shaft_radius) * 100, 0), TASK.fixture.shaft_radius * 200,
                               TASK.top[2] * 100, color="0.6", ec="k", label="shaft"))
        for k, tcp in enumerate(paths[name]):
            ax.plot(tcp[:, 0] * 100, tcp[:, 2] * 100, "-", color="r", lw=0.9, alpha=0.8,
                    label="TCP paths (gear's lower face)" if k == 0 else None)
        ax.plot(TASK.top[0] * 100, (TASK.top[2] - 0.02) * 100, "*", color="w", ms=12)
        ax.set_aspect("equal")
        ax.set_xlim(xs[0] * 100, xs[-1] * 100)
        ax.set_ylim(zs[0] * 100, zs[-1] * 100)
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("z (cm)")
        ax.set_title(name, fontsize=9)
        ax.legend(loc="upper left", fontsize=7)
    fig.colorbar(cs, ax=list(axes[0]), shrink=0.85, label="V = 1/2 |phi(x) - phi(x_ref)|_S^2 (J), y = 0")
    fig.suptitle("gear_clamp: one quadratic well vs. the hand-built flow (same S, D)", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--png", type=Path, help="draw V on the x-z slice with the episodes' TCP paths here")
    args = ap.parse_args()
    cfg = TrainConfig.from_sources(CONFIG)
    plain = Trainer(cfg)
    set_gains(plain)
    shaped = Trainer(cfg)
    identity = shaped.policy.flow.to_flat()
    fit = build(shaped)
    set_gains(shaped)
    print("lift (target, fit) in mm at x =",
          ", ".join(f"{x:.2f}: {t * 1e3:.0f}/{f * 1e3:.0f}" for x, t, f in fit[::25]))
    x_ref = shaped.policy.x_ref.numpy()
    change = (rescale_flow_weights(shaped.policy.arch, shaped.policy.flow.to_flat(), x_ref, cfg.flow_input_scale,
                                   inverse=True)
              - rescale_flow_weights(shaped.policy.arch, identity, x_ref, cfg.flow_input_scale, inverse=True))
    print(f"change of the flow's weights in the explored (normalised) units: norm {np.linalg.norm(change):.2f}, "
          f"largest entry {np.abs(change).max():.2f}")
    well = f"identity flow (one quadratic well),\nS = diag{tuple(S_DIAG)}, D = diag{tuple(D_DIAG)}"
    built = "the same S, D with the hand-built flow"
    recs = {well: evaluate(plain, args.episodes), built: evaluate(shaped, args.episodes)}
    for name, r in recs.items():
        report(name.replace("\n", " "), r)
    if args.png:
        named = {f"{k}\n{sum(r.final_success for r in v)}/{len(v)} inserted": v for k, v in recs.items()}
        plot(args.png, dict(zip(named, (plain.policy, shaped.policy), strict=True)),
             {k: [r.x for r in v] for k, v in named.items()})


if __name__ == "__main__":
    main()
