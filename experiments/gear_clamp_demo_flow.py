"""gear_clamp: a flow initialised from a hand-written demonstration, as a checkpoint PPO can start from.

The demonstration (``demo_waypoints``) is written by hand, not recorded and not learned: from each of
18 starts on a grid over the task's start region (TCP x 0.70/0.715/0.73 m, y -0.05/0/0.05 m,
z 0.11/0.14 m), towards the clamp at the start's height until the gear's rim is 3 cm from its face,
up to z = Z_OVER while closing in to 0.5 cm, over the clamp to above the shaft and straight down to
x_ref = (0.5, 0, 0.07) m: five waypoints per path. (The lift has to be made while x still moves
towards the goal: in this architecture the latent z is z e^{s(x)} + t(x), strictly increasing in z at
a fixed x, and an overdamped latent coordinate never reverses, so a flow of it makes "straight up,
then over, then straight down" a controller path only by stretching latent x hugely against latent z:
fitted to such a demonstration without the regulariser below, J's singular values spread over
0.001-135 in the workspace and the arm was thrown about, 0/10.)

``learner_node.flow_fit`` fits the flow of config/gear_clamp.yaml (n_flow 1, n_hidden 16, gelu,
flow_input_scale 0.05; all 1350 weights, from seed 0's identity initialisation) so that along these
paths the latent velocity points along the overdamped latent motion -S D^-1 (phi(x) - phi(x_ref)),
with |J - I|^2 over the workspace as a regulariser. S and D are the hand-built flow's
(experiments/gear_clamp_handflow.py): diag(400, 400, 135) N/m and diag(40, 40, 100) N s/m, a slow latent
z, so the gear is carried over first and lowered last. Writes the policy as a checkpoint of a
0-iteration run (``--out``, for ``train_cli --set init_checkpoint=...``), evaluates it
deterministically on held-out starts and can draw V over the x-z slice, with the same S, D and the
identity flow and with learned controllers (``--runs``) next to it.

    python experiments/gear_clamp_demo_flow.py --out /tmp/demo/demo_prior.pt [--episodes 10] [--eval-offset 0]
        [--json JSON] [--png PNG --runs RUN_DIR ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from learner_node.analysis.flow_landscape import load_policy
from learner_node.config import TrainConfig
from learner_node.flow_fit import demo_samples, fit_flow_to_demos, latent_cosines
from learner_node.policy import NFPolicy
from learner_node.trainer import EVAL_SEED_BASE, Trainer, make_evaluator
from nf_core.task_spec import load_task

TASK = load_task("gear_clamp")

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_clamp.yaml"
Z_OVER = 0.32  # m: TCP height of the carry over the clamp (its top: 0.20 m, the gear's rim: r = 3 cm)
X_RAMP0, X_RAMP1 = 0.68, 0.655  # m: TCP x where the lift starts and ends (the rim meets the clamp at 0.65)
STARTS_X, STARTS_Y, STARTS_Z = (0.70, 0.715, 0.73), (-0.05, 0.0, 0.05), (0.11, 0.14)


def demo_waypoints(x_ref: np.ndarray) -> list[np.ndarray]:
    """The hand-written demonstration from 18 starts: towards the clamp at the start's height until the
    gear's rim is 3 cm from the clamp's face (TCP x = X_RAMP0), up to Z_OVER while closing to 0.5 cm
    from it (X_RAMP1), over the clamp to above the shaft and down onto it."""
    paths = []
    for x0 in STARTS_X:
        for y0 in STARTS_Y:
            for z0 in STARTS_Z:
                paths.append(np.array([[x0, y0, z0], [X_RAMP0, y0, z0], [X_RAMP1, 0.5 * y0, Z_OVER],
                                       [x_ref[0], x_ref[1], Z_OVER - 0.03], x_ref]))
    return paths


def workspace_grid() -> np.ndarray:
    """Points over the workspace (x 0.45-0.78 m, |y| <= 0.08 m, z 0.05-0.35 m) where |J - I| is kept small."""
    axes = np.linspace(0.45, 0.78, 9), np.linspace(-0.08, 0.08, 5), np.linspace(0.05, 0.35, 9)
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def build(cfg: TrainConfig, stiffness: np.ndarray, damping: np.ndarray, iterations: int,
          jacobian_weight: float) -> tuple[Trainer, dict]:
    """A 0-iteration trainer whose policy has the demo-fitted flow and S = diag(stiffness),
    D = diag(damping); the fit's latent rates are S D^-1."""
    trainer = Trainer(cfg)
    pol = trainer.policy
    x_ref = pol.x_ref.numpy()
    rates = stiffness / damping
    samples = [demo_samples(w) for w in demo_waypoints(x_ref)]
    points = np.concatenate([p for p, _ in samples])
    tangents = np.concatenate([t for _, t in samples])
    before = float(latent_cosines(pol.flow, x_ref, points, tangents, rates).mean())
    t0 = time.time()
    fit = fit_flow_to_demos(pol.flow, x_ref, cfg.flow_input_scale, points, tangents, iterations=iterations,
                            rates=rates, jacobian_points=workspace_grid(), jacobian_weight=jacobian_weight)
    with torch.no_grad():
        pol.ln_s.copy_(torch.log(torch.as_tensor(stiffness, dtype=pol.ln_s.dtype)))
        pol.ln_d.copy_(torch.log(torch.as_tensor(damping, dtype=pol.ln_d.dtype)))
    pol.sync_gains()
    cos = latent_cosines(pol.flow, x_ref, points, tangents, rates)
    with torch.no_grad():
        _, jac = pol.flow.phi_and_jacobian_autograd(torch.as_tensor(workspace_grid()))
    sv = np.linalg.svd(jac.numpy(), compute_uv=False)
    info = {"demo_points": len(points), "demo_paths": len(samples), "fit_iterations": iterations,
            "jacobian_weight": jacobian_weight, "fit_seconds": round(time.time() - t0, 1),
            "loss_start": fit.loss_start, "loss_end": fit.loss_end, "mean_cos_before": before,
            "mean_cos_after": float(cos.mean()), "cos_after_5th_percentile": float(np.percentile(cos, 5)),
            "normalised_change_norm": float(np.linalg.norm(fit.normalised - fit.normalised_start)),
            "workspace_singular_values_range": [float(sv.min()), float(sv.max())],
            "stiffness": stiffness.tolist(), "damping": damping.tolist()}
    return trainer, info


def evaluate(trainer: Trainer, policy: NFPolicy, n: int, offset: int = 0) -> list:
    """Deterministic episodes of ``policy`` from the held-out starts ``offset`` .. ``offset + n - 1``."""
    ev = make_evaluator(policy)
    return [trainer.runner.run_episode(ev, None, EVAL_SEED_BASE + offset + k, None) for k in range(n)]


def summary(recs: list) -> dict:
    ok = [bool(r.final_success) for r in recs]
    return {"inserted": int(sum(ok)), "episodes": len(recs), "success": ok,
            "highest_tcp_z": float(max(r.x[:, 2].max() for r in recs)),
            "final_tcp": [np.round(r.x[-1], 4).tolist() for r in recs],
            "mean_torque_norm": float(np.mean([r.torque_norm for r in recs]))}


def plot(path: Path, columns: list[tuple[str, NFPolicy, list]]) -> None:
    """V on the x-z slice through the shaft axis (y = 0) per policy (title, policy, episodes), the clamp,
    the shaft and the demonstration drawn, with the TCP paths of the evaluation episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle


    xs, zs = np.linspace(0.42, 0.78, 145), np.linspace(0.04, 0.36, 129)
    gx, gz = np.meshgrid(xs, zs)
    pts = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1)
    fig, axes = plt.subplots(1, len(columns), figsize=(5.6 * len(columns), 5.2), squeeze=False)
    for ax, (title, pol, recs) in zip(axes[0], columns, strict=True):
        with torch.no_grad():
            v = pol.lyapunov_potential(torch.from_numpy(pts)).numpy().reshape(gx.shape)
        levels = np.geomspace(1e-4 * float(v.max()), float(v.max()), 25)
        cs = ax.contourf(gx * 100, gz * 100, np.clip(v, levels[0], None), levels=levels, cmap="viridis",
                         norm=LogNorm())
        ax.contour(gx * 100, gz * 100, np.clip(v, levels[0], None), levels=levels, colors="k", linewidths=0.3,
                   alpha=0.5)
        c0 = TASK.clamp.center_x - TASK.clamp.half_thickness
        ax.add_patch(Rectangle((c0 * 100, 0), 2 * TASK.clamp.half_thickness * 100, TASK.clamp.top * 100,
                               color="0.85", ec="k", label="clamp"))
        ax.add_patch(Rectangle(((TASK.top[0] - TASK.fixture.shaft_radius) * 100, 0), TASK.fixture.shaft_radius * 200,
                               TASK.top[2] * 100, color="0.6", ec="k", label="shaft"))
        x_ref = pol.x_ref.numpy()
        for k, w in enumerate(w for w in demo_waypoints(x_ref) if abs(w[0, 1]) < 1e-9):
            ax.plot(w[:, 0] * 100, w[:, 2] * 100, "--", color="w", lw=0.8,
                    label="demonstration (y = 0 starts)" if k == 0 else None)
        for k, r in enumerate(recs):
            ax.plot(r.x[:, 0] * 100, r.x[:, 2] * 100, "-", color="r", lw=0.9, alpha=0.8,
                    label="TCP paths, held-out starts" if k == 0 else None)
        ax.plot(x_ref[0] * 100, x_ref[2] * 100, "*", color="w", ms=12)
        ax.set_aspect("equal")
        ax.set_xlim(xs[0] * 100, xs[-1] * 100)
        ax.set_ylim(zs[0] * 100, zs[-1] * 100)
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("z (cm)")
        ax.set_title(f"{title}\n{sum(r.final_success for r in recs)}/{len(recs)} inserted (deterministic)",
                     fontsize=8)
        ax.legend(loc="upper left", fontsize=6)
        fig.colorbar(cs, ax=ax, shrink=0.8, label="V = 1/2 |phi(x) - phi(x_ref)|_S^2 (J), y = 0")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def gains_text(pol: NFPolicy) -> str:
    S, D = (np.round(torch.diagonal(m).detach().numpy()).astype(int).tolist() for m in pol.gains())
    return f"S = diag{tuple(S)}, D = diag{tuple(D)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="write the checkpoint here")
    ap.add_argument("--stiffness", type=float, nargs=3, default=[400.0, 400.0, 135.0], help="diagonal of S, N/m")
    ap.add_argument("--damping", type=float, nargs=3, default=[40.0, 40.0, 100.0], help="diagonal of D, N s/m")
    ap.add_argument("--fit-iterations", type=int, default=300)
    ap.add_argument("--jacobian-weight", type=float, default=1e-2, help="weight of mean |J - I|^2 over the workspace")
    ap.add_argument("--episodes", type=int, default=10, help="deterministic held-out evaluation (0: none)")
    ap.add_argument("--eval-offset", type=int, default=0,
                    help="first held-out start (the training's evaluation uses 0-9; others are fresh starts)")
    ap.add_argument("--json", type=Path, help="write the fit's and the evaluation's numbers here")
    ap.add_argument("--png", type=Path, help="draw V on the x-z slice with the episodes' TCP paths here: the same "
                    "S, D with the identity flow, the demo-fitted flow and each --runs folder's learned controller")
    ap.add_argument("--runs", type=Path, nargs="*", default=[], help="train_cli run folders to draw (--png)")
    args = ap.parse_args()
    cfg = TrainConfig.from_sources(CONFIG)
    trainer, info = build(cfg, np.asarray(args.stiffness), np.asarray(args.damping), args.fit_iterations,
                          args.jacobian_weight)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    trainer.save_checkpoint(args.out)
    print(json.dumps(info))
    pol = trainer.policy
    columns = []
    if args.episodes:
        recs = evaluate(trainer, pol, args.episodes, args.eval_offset)
        info["evaluation"] = {"starts": [args.eval_offset, args.eval_offset + args.episodes - 1], **summary(recs)}
        print(f"demo flow, {gains_text(pol)}: {info['evaluation']['inserted']}/{len(recs)} inserted; highest TCP z "
              f"{info['evaluation']['highest_tcp_z']:.3f} m; final TCP {info['evaluation']['final_tcp']}")
        columns.append((f"flow fitted to the demonstration (the prior),\n{gains_text(pol)}", pol, recs))
    if args.episodes:
        well = Trainer(cfg).policy  # identity flow, the same S, D: one quadratic well
        with torch.no_grad():
            well.ln_s.copy_(pol.ln_s)
            well.ln_d.copy_(pol.ln_d)
        well.sync_gains()
        recs = evaluate(trainer, well, args.episodes, args.eval_offset)
        info["identity_flow_same_gains"] = summary(recs)
        columns.insert(0, (f"identity flow (one quadratic well),\n{gains_text(well)}", well, recs))
        info["runs"] = {}
        for run in args.runs:
            _, learned = load_policy(run)
            recs = evaluate(trainer, learned, args.episodes, args.eval_offset)
            info["runs"][run.name] = summary(recs)
            print(f"{run.name}: {info['runs'][run.name]['inserted']}/{len(recs)} inserted")
            columns.append((f"after PPO: {run.name},\n{gains_text(learned)}", learned, recs))
        print(f"identity flow, same S, D: {info['identity_flow_same_gains']['inserted']}/{args.episodes} inserted")
    if args.png and columns:
        plot(args.png, columns)
    if args.json:
        args.json.write_text(json.dumps(info, indent=1) + "\n")


if __name__ == "__main__":
    main()
