"""``fit_demos``: a policy from recorded demonstrations (bags), ready for learning to refine.

Each demonstration is an episode of a bag (``teach`` records them; the controller's status says when
an episode ran) or, in a bag without episodes (hand-guiding), the whole recording. Its TCP path comes
from the recorded joint states by forward kinematics (Pinocchio, the held part's TCP). The flow of the
task's learner settings is fitted so that these paths become the controller's own
(``learner_node.flow_fit``: Euclideanizing flows' cosine loss, with |J - I|^2 over the workspace as the
regulariser), the gains are set, and the policy is written as an ordinary checkpoint with its law:
``train_cli --set init_checkpoint=<out>/checkpoint.pt`` or ``make run ARGS="--from-checkpoint ..."``
refine it. Whatever the fit gives, the policy is the provably stable controller (a bijection phi for any
weights, S and D positive definite).

    python -m nf_bags.fit_demos runs/teach-X/bag --config config/gear_clamp.yaml --out runs/teach-X/fit

Writes ``checkpoint.pt``, ``fit.json`` (the demonstrations used and left out, the fit's numbers, the
prior's deterministic evaluation on the held-out starts) and ``landscape.png`` (V on the vertical slice
through the goal with the demonstrations and the prior's paths drawn).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from learner_node.config import TrainConfig, parse_sets
from learner_node.flow_fit import demo_basis, demo_samples, fit_flow_to_demos, latent_cosines
from learner_node.policy import NFPolicy
from learner_node.trainer import EVAL_SEED_BASE, Trainer, make_evaluator
from nf_core.task_spec import TaskSpec, load_task

RUNNING = 1  # nf_msgs/ControllerStatus.MODE_RUNNING
# a simulator's reset, not a motion: a step of more than 2 cm between two recorded states, faster than 2 m/s
# (a robot's states may be further apart when their publisher was late, but the arm moved in between)
TELEPORT = 0.02  # m
TELEPORT_SPEED = 2.0  # m/s
REACHED = 0.02  # m: a demonstration that ends farther than this from the goal shows no way there; left out
# S = diag(400, 400, 135) N/m, D = diag(40, 40, 100) N s/m: a stiff, quick carry across and a soft, slow
# latent z (the part is carried over first and lowered last; docs/results/gear_clamp)
DEMO_SHIFT = 0.01  # m: a unit along a direction of the demonstrations' space (learning explores 1 unit std)
DEMO_STIFFNESS = (400.0, 400.0, 135.0)
DEMO_DAMPING = (40.0, 40.0, 100.0)


def episode_windows(bag: str | Path) -> list[tuple[int, int]]:
    """(first, last) stamp (ns) of each episode the controller's status reports running (by episode id)."""
    from .reader import CONTROLLER_STATUS, read_messages, stamp_ns

    windows: list[list[int]] = []
    last = None  # the episode id of the previous status (None: not running)
    for d in read_messages(bag, [CONTROLLER_STATUS]):
        now = int(d.msg.episode_id) if d.msg.mode == RUNNING and d.msg.episode_id else None
        t = stamp_ns(d.msg.header)
        if now is not None and now != last:
            windows.append([t, t])
        elif now is not None:
            windows[-1][1] = t
        last = now
    return [(a, b) for a, b in windows]


def demo_paths(bag: str | Path, task: TaskSpec) -> list[np.ndarray]:
    """TCP paths (m, (n, 3) each) of the demonstrations in ``bag``: the joint states of each episode (or,
    without episodes, of the whole bag) through the forward kinematics of the arm holding ``task``'s part."""
    from nf_controller_node.arm_model import ArmModel
    from nf_core.task_spec import held_part_inertia

    from .reader import joint_trajectory

    traj = joint_trajectory(bag)
    if len(traj.stamp_ns) == 0:
        raise ValueError(f"{bag}: no joint states recorded")
    arm = ArmModel(part=held_part_inertia(task.part.text()))
    windows = episode_windows(bag) or [(int(traj.stamp_ns[0]), int(traj.stamp_ns[-1]))]
    paths = []
    for a, b in windows:
        rows = np.flatnonzero((traj.stamp_ns >= a) & (traj.stamp_ns <= b))
        if len(rows) > 1:
            path = np.array([arm.tcp_position(traj.q[i]) for i in rows])
            step = np.linalg.norm(np.diff(path, axis=0), axis=1)
            dt = np.maximum(np.diff(traj.stamp_ns[rows]) * 1e-9, 1e-9)
            jumps = np.flatnonzero((step > TELEPORT) & (step / dt > TELEPORT_SPEED))
            paths.append(path[jumps[-1] + 1 :] if len(jumps) else path)  # from the reset on
    return paths


def workspace_grid(task: TaskSpec) -> np.ndarray:
    """Points around the task (from the goal to the starts and above the clamp) where |J - I| is kept small:
    9 x 5 x 9 over x from the goal - 5 cm to the starts + 5 cm, y +-8 cm, z from the goal - 2 cm to 35 cm."""
    goal, start = task.goal_position, task.start_tcp
    top = max(0.35, (task.clamp.top + 0.15) if task.clamp is not None else start[2] + 0.05)
    axes = (np.linspace(min(goal[0], start[0]) - 0.05, max(goal[0], start[0]) + 0.05, 9),
            np.linspace(goal[1] - 0.08, goal[1] + 0.08, 5), np.linspace(goal[2] - 0.02, top, 9))
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def fit_policy(trainer: Trainer, task: TaskSpec, paths: list[np.ndarray], stiffness: np.ndarray,
               damping: np.ndarray, iterations: int = 300, jacobian_weight: float = 1e-2) -> dict:
    """Fit ``trainer``'s policy (in place) to ``paths``: the flow so that they follow the overdamped latent
    motion -S D^-1 (phi(x) - phi(x_ref)), S = diag(``stiffness``), D = diag(``damping``). Returns the fit's numbers."""
    pol = trainer.policy
    x_ref = pol.x_ref.numpy()
    rates = np.asarray(stiffness) / np.asarray(damping)
    samples = [demo_samples(p) for p in paths]
    points = np.concatenate([p for p, _ in samples])
    tangents = np.concatenate([t for _, t in samples])
    before = float(latent_cosines(pol.flow, x_ref, points, tangents, rates).mean())
    t0 = time.time()
    grid = workspace_grid(task)
    fit = fit_flow_to_demos(pol.flow, x_ref, trainer.cfg.flow_input_scale, points, tangents, iterations=iterations,
                            rates=rates, jacobian_points=grid, jacobian_weight=jacobian_weight)
    with torch.no_grad():
        pol.ln_s.copy_(torch.log(torch.as_tensor(np.asarray(stiffness), dtype=pol.ln_s.dtype)))
        pol.ln_d.copy_(torch.log(torch.as_tensor(np.asarray(damping), dtype=pol.ln_d.dtype)))
    pol.sync_gains()
    cos = latent_cosines(pol.flow, x_ref, points, tangents, rates)
    with torch.no_grad():
        _, jac = pol.flow.phi_and_jacobian_autograd(torch.as_tensor(grid))
    sv = np.linalg.svd(jac.numpy(), compute_uv=False)
    return {"demo_paths": len(paths), "demo_points": len(points), "fit_iterations": iterations,
            "jacobian_weight": jacobian_weight, "fit_seconds": round(time.time() - t0, 1),
            "loss_start": fit.loss_start, "loss_end": fit.loss_end, "mean_cos_before": before,
            "mean_cos_after": float(cos.mean()), "cos_after_5th_percentile": float(np.percentile(cos, 5)),
            "normalised_change_norm": float(np.linalg.norm(fit.normalised - fit.normalised_start)),
            "workspace_singular_values_range": [float(sv.min()), float(sv.max())],
            "stiffness": list(map(float, stiffness)), "damping": list(map(float, damping))}


def evaluate(trainer: Trainer, policy: NFPolicy, n: int, offset: int = 0) -> list:
    """Deterministic episodes of ``policy`` from the held-out starts ``offset`` .. ``offset + n - 1``."""
    ev = make_evaluator(policy)
    return [trainer.runner.run_episode(ev, None, EVAL_SEED_BASE + offset + k, None) for k in range(n)]


def summary(recs: list) -> dict:
    """Inserted count, per-episode success, highest TCP z and final TCP of evaluation episodes."""
    ok = [bool(r.final_success) for r in recs]
    return {"inserted": int(sum(ok)), "episodes": len(recs), "success": ok,
            "highest_tcp_z": float(max(r.x[:, 2].max() for r in recs)),
            "final_tcp": [np.round(r.x[-1], 4).tolist() for r in recs]}


def gains_text(pol: NFPolicy) -> str:
    """``S = diag(..), D = diag(..)`` rounded."""
    S, D = (np.round(torch.diagonal(m).detach().numpy()).astype(int).tolist() for m in pol.gains())
    return f"S = diag{tuple(S)}, D = diag{tuple(D)}"


def plot_landscape(path: Path, task: TaskSpec, columns: list[tuple[str, NFPolicy, list]],
                   demos: list[np.ndarray] = ()) -> None:
    """V on the vertical x-z slice through the goal for each (title, policy, evaluation episodes), with the
    fixture, the clamp (if any), the demonstrations (white) and the episodes' TCP paths (red) drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    grid = workspace_grid(task)
    xs = np.linspace(grid[:, 0].min() - 0.03, grid[:, 0].max() + 0.03, 145)
    zs = np.linspace(max(grid[:, 2].min() - 0.03, 0.0), grid[:, 2].max() + 0.01, 129)
    y0 = float(task.goal_position[1])
    gx, gz = np.meshgrid(xs, zs)
    pts = np.stack([gx.ravel(), np.full(gx.size, y0), gz.ravel()], 1)
    fig, axes = plt.subplots(1, len(columns), figsize=(5.6 * len(columns), 5.2), squeeze=False)
    for ax, (title, pol, recs) in zip(axes[0], columns, strict=True):
        with torch.no_grad():
            v = pol.lyapunov_potential(torch.from_numpy(pts)).numpy().reshape(gx.shape)
        levels = np.geomspace(1e-4 * float(v.max()), float(v.max()), 25)
        cs = ax.contourf(gx * 100, gz * 100, np.clip(v, levels[0], None), levels=levels, cmap="viridis",
                         norm=LogNorm())
        if task.clamp is not None:
            c = task.clamp
            ax.add_patch(Rectangle(((c.center_x - c.half_thickness) * 100, 0), 2 * c.half_thickness * 100,
                                   c.top * 100, color="0.85", ec="k", label="clamp"))
        half = task.fixture.shaft_radius if task.kind != "peg" else task.fixture.hole_half_width
        ax.add_patch(Rectangle(((task.top[0] - half) * 100, 0), half * 200, task.top[2] * 100, color="0.6", ec="k",
                               label="fixture"))
        for k, p in enumerate(demos):
            ax.plot(p[:, 0] * 100, p[:, 2] * 100, "--", color="w", lw=0.8, label="demonstrations" if k == 0 else None)
        for k, r in enumerate(recs):
            ax.plot(r.x[:, 0] * 100, r.x[:, 2] * 100, "-", color="r", lw=0.9, alpha=0.8,
                    label="TCP paths, held-out starts" if k == 0 else None)
        x_ref = pol.x_ref.numpy()
        ax.plot(x_ref[0] * 100, x_ref[2] * 100, "*", color="w", ms=12)
        ax.set_aspect("equal")
        ax.set_xlim(xs[0] * 100, xs[-1] * 100)
        ax.set_ylim(zs[0] * 100, zs[-1] * 100)
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("z (cm)")
        ok = f"{sum(r.final_success for r in recs)}/{len(recs)} inserted (deterministic)" if recs else ""
        ax.set_title(f"{title}\n{ok}", fontsize=8)
        ax.legend(loc="upper left", fontsize=6)
        fig.colorbar(cs, ax=ax, shrink=0.8, label=f"V = 1/2 |phi(x) - phi(x_ref)|_S^2 (J), y = {y0:g} m")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Console script ``fit_demos``."""
    ap = argparse.ArgumentParser(prog="fit_demos", description=__doc__.split("\n\n")[0])
    ap.add_argument("bags", type=Path, nargs="+", help="bags of demonstrations (teach's <out>/bag, ...)")
    ap.add_argument("--config", type=Path, action="append", required=True,
                    help="the learner's settings (task file, overlays): the flow's architecture, the goal")
    ap.add_argument("--task", default=None, help="the task (default: the settings' task)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="any other learner setting, e.g. --set potential_force_bound=60 (the law's pull bound, "
                         "for an arm; repeatable)")
    ap.add_argument("--out", type=Path, required=True, help="folder for checkpoint.pt, fit.json, landscape.png")
    ap.add_argument("--max-demos", type=int, default=0, help="use only the first N demonstrations (0: all)")
    ap.add_argument("--stiffness", type=float, nargs=3, default=DEMO_STIFFNESS, help="diagonal of S, N/m")
    ap.add_argument("--damping", type=float, nargs=3, default=DEMO_DAMPING, help="diagonal of D, N s/m")
    ap.add_argument("--fit-iterations", type=int, default=300, help="Adam steps of the fit")
    ap.add_argument("--jacobian-weight", type=float, default=1e-2, help="weight of mean |J - I|^2 over the workspace")
    ap.add_argument("--episodes", type=int, default=10, help="deterministic held-out evaluation of the prior (0: none)")
    ap.add_argument("--seed", type=int, default=0, help="the learner's seed (its flow's initialisation)")
    ap.add_argument("--explore-std", type=float, default=0.2,
                    help=f"std of learning's exploration along the demonstrations' directions, in units of a "
                         f"{100 * DEMO_SHIFT:g} cm move of the demonstrations (default 0.2: 2 mm); 0: the "
                         "learner's own random directions")
    args = ap.parse_args(argv)
    overrides: dict[str, object] = {"seed": args.seed, **({"task": args.task} if args.task else {})}
    try:
        overrides.update(parse_sets(args.sets))
        cfg = TrainConfig.from_sources(args.config, overrides)
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))
    task = load_task(cfg.task)
    paths, left_out = [], []
    for bag in args.bags:
        for k, p in enumerate(demo_paths(bag, task)):
            miss = float(np.linalg.norm(p[-1] - task.goal_position))
            (left_out if miss > REACHED else paths).append(p)
            if miss > REACHED:
                print(f"[fit] {bag} demonstration {k}: ends {1e3 * miss:.0f} mm from the goal; left out", flush=True)
    if args.max_demos:
        paths = paths[: args.max_demos]
    if not paths:
        print("[fit] no demonstration reaches the goal: nothing to fit", file=sys.stderr)
        return 2
    trainer = Trainer(cfg)
    print(f"[fit] {len(paths)} demonstration(s) ({len(left_out)} left out); fitting the flow "
          f"(n_flow {cfg.n_flow}, n_hidden {cfg.n_hidden}) ...", flush=True)
    info = fit_policy(trainer, task, paths, np.asarray(args.stiffness), np.asarray(args.damping),
                      args.fit_iterations, args.jacobian_weight)
    info |= {"bags": [str(b) for b in args.bags], "left_out": len(left_out), "task": cfg.task}
    if trainer.explorer is not None and cfg.param_sigma_flow > 0.0 and args.explore_std > 0.0:
        # learning explores the flow in the demonstrations' space
        t0 = time.time()
        pol = trainer.policy
        basis = demo_basis(pol.flow, pol.x_ref.numpy(), cfg.flow_input_scale, paths, shift=DEMO_SHIFT,
                           rates=np.asarray(args.stiffness) / np.asarray(args.damping),
                           jacobian_points=workspace_grid(task), jacobian_weight=args.jacobian_weight)
        trainer.explorer.use_basis(basis, sigma=args.explore_std)
        trainer.update_rule.restart_optimizer()
        info["demo_basis"] = {"directions": basis.shape[1], "shift_m": DEMO_SHIFT, "std": args.explore_std,
                              "seconds": round(time.time() - t0, 1),
                              "column_norms": np.round(np.linalg.norm(basis, axis=0), 3).tolist()}
        print(f"[fit] learning will explore the flow along {basis.shape[1]} directions of the demonstrations' space "
              f"(std {args.explore_std:g} x {100 * DEMO_SHIFT:g} cm; {info['demo_basis']['seconds']} s)", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    trainer.save_checkpoint(args.out / "checkpoint.pt")
    pol = trainer.policy
    print(f"[fit] mean cos {info['mean_cos_before']:.3f} -> {info['mean_cos_after']:.3f}, weights moved by "
          f"{info['normalised_change_norm']:.2f}, J's singular values {info['workspace_singular_values_range']} "
          f"over the workspace; {gains_text(pol)}; checkpoint {args.out / 'checkpoint.pt'}", flush=True)
    columns = [("flow fitted to the demonstrations (the prior),\n" + gains_text(pol), pol, [])]
    if args.episodes:
        recs = evaluate(trainer, pol, args.episodes)
        info["evaluation"] = summary(recs)
        columns = [(columns[0][0], pol, recs)]
        print(f"[fit] the prior on {args.episodes} held-out starts: {info['evaluation']['inserted']}/{args.episodes} "
              "inserted (deterministic)", flush=True)
    plot_landscape(args.out / "landscape.png", task, columns, paths)
    (args.out / "fit.json").write_text(json.dumps(info, indent=1) + "\n")
    print(f"[fit] {args.out / 'fit.json'}, {args.out / 'landscape.png'}; refine: python -m learner_node.train_cli "
          f"--config {args.config[0]} --set init_checkpoint={args.out / 'checkpoint.pt'}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
