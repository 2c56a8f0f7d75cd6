"""How far a learned arm flow is from the identity, and its potential V over slices of the workspace.

``python -m learner_node.analysis.flow_landscape RUN_DIR [RUN_DIR ...] --out PNG --json JSON``

For each run folder (``train --out``): the coupling nets' output-layer norms (the weights that are
zero in the identity initialisation), and max |phi(x) - phi(x_ref) - (x - x_ref)| (the flow's
departure from a pure translation, m) over a local box (+-3 cm around x_ref) and an approach box
(+-10 cm laterally, 0-15 cm above x_ref). The picture (first run) shows V(x, xdot=0) =
1/2 e^T S e, e = phi(x) - phi(x_ref), on the vertical slices y = y_ref (x-z) and x = x_ref (y-z) for
the prior (its S, identity flow), the learned gains with the flow reset to the identity, and the
learned controller (flow + gains): what the flow adds is the difference of the last two columns.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..config import TrainConfig
from ..flow import init_flow_weights, output_layer_mask
from ..policy import NFPolicy
from ..trainer import CHECKPOINT, build_policy

LOCAL_BOX = (np.array([-0.03, -0.03, -0.03]), np.array([0.03, 0.03, 0.03]))  # m around x_ref
APPROACH_BOX = (np.array([-0.10, -0.10, 0.0]), np.array([0.10, 0.10, 0.15]))


def load_policy(run_dir: Path) -> tuple[TrainConfig, NFPolicy]:
    """The config and the NF policy of a run folder's last checkpoint."""
    raw = json.loads((run_dir / "config.json").read_text())
    cfg = TrainConfig.from_sources(None, TrainConfig.with_defaults(raw))
    state = torch.load(run_dir / CHECKPOINT, weights_only=True)
    policy = build_policy(cfg, np.zeros(cfg.dim))
    policy.load_state_dict(state["policy"])
    policy.sync_gains()
    return cfg, policy


def identity_flow_copy(policy: NFPolicy, stiffness: np.ndarray | None = None) -> NFPolicy:
    """The same gains and goal with the flow reset to the identity (``stiffness``: another S)."""
    with torch.no_grad():
        S, D = policy.gains()
    arch = policy.arch
    w = init_flow_weights(arch, np.random.default_rng(0), init="identity")
    return NFPolicy(arch, weights=w, stiffness=S.numpy() if stiffness is None else stiffness,
                    damping=D.numpy(), x_ref=policy.x_ref.numpy())


def box_grid(box: tuple[np.ndarray, np.ndarray], n: int = 11) -> np.ndarray:
    """Offsets (n^3, 3) on a regular grid of ``box``."""
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(*box, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def flow_distance(policy: NFPolicy) -> dict[str, Any]:
    """Output-layer norms and the flow's departure from a translation over the two boxes."""
    w = policy.flow.to_flat()
    mask = output_layer_mask(policy.arch)
    x_ref = policy.x_ref.numpy()
    out: dict[str, Any] = {"output_layer_norm": float(np.linalg.norm(w[mask])),
                           "output_layer_max_abs": float(np.abs(w[mask]).max())}
    with torch.no_grad():
        phi_ref = policy.flow(torch.from_numpy(x_ref[None]))[0].numpy()
        for name, box in (("local_3cm", LOCAL_BOX), ("approach", APPROACH_BOX)):
            off = box_grid(box)
            phi = policy.flow(torch.from_numpy(x_ref + off)).numpy()
            dev = np.linalg.norm(phi - phi_ref - off, axis=1)
            _, jac = policy.flow.phi_and_jacobian(torch.from_numpy(x_ref + off))
            sv = np.linalg.svd(jac.numpy(), compute_uv=False)
            out[name] = {"max_departure_m": float(dev.max()), "mean_departure_m": float(dev.mean()),
                         "jacobian_sv_min": float(sv.min()), "jacobian_sv_max": float(sv.max())}
    return out


def _slice_potential(policy: NFPolicy, a: np.ndarray, b: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    x_ref = policy.x_ref.numpy()
    ga, gb = np.meshgrid(a, b)
    pts = np.repeat(x_ref[None], ga.size, axis=0)
    pts[:, axes[0]] += ga.ravel()
    pts[:, axes[1]] += gb.ravel()
    with torch.no_grad():
        return policy.lyapunov_potential(torch.from_numpy(pts)).numpy().reshape(ga.shape)


def plot_landscape(columns: dict[str, NFPolicy], path: Path, title: str, grid: int = 81) -> Path:
    """V over the x-z (y = y_ref) and y-z (x = x_ref) slices, one column per policy, log-scaled contours
    with one colour scale per row (in J)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    lat = np.linspace(APPROACH_BOX[0][0], APPROACH_BOX[1][0], grid)
    ax_z = np.linspace(-0.03, APPROACH_BOX[1][2], grid)
    n = len(columns) + 1  # last column: the last policy's V over the one before it (what the flow adds)
    fig, axes = plt.subplots(2, n, figsize=(4.6 * n, 8.2), squeeze=False)
    for r, (plane, label) in enumerate((((0, 2), "x"), ((1, 2), "y"))):
        vs = {k: _slice_potential(p, lat, ax_z, plane) for k, p in columns.items()}
        vmax = max(float(v.max()) for v in vs.values())
        vmin = max(min(float(v.min()) for v in vs.values()), 1e-5 * vmax)
        levels = np.geomspace(vmin, vmax, 24)
        for c, (name, v) in enumerate(vs.items()):
            ax = axes[r, c]
            cs = ax.contourf(lat * 100, ax_z * 100, np.clip(v, vmin, None), levels=levels, cmap="viridis",
                             norm=LogNorm())
            ax.contour(lat * 100, ax_z * 100, np.clip(v, vmin, None), levels=levels, colors="k",
                       linewidths=0.3, alpha=0.5)
            ax.plot(0, 0, "*", color="r", ms=11)
            ax.axhspan(-3, 0, color="w", alpha=0.15)  # below the goal: inside the fixture
            ax.set_aspect("equal")
            ax.set_title(f"{name}\nV on the {label}-z slice", fontsize=9)
            ax.set_xlabel(f"{label} - {label}_ref (cm)")
            ax.set_ylabel("z - z_ref (cm)")
        fig.colorbar(cs, ax=list(axes[r][:-1]), shrink=0.8, label="V (J)")
        names = list(vs)
        ratio = np.log2(np.maximum(vs[names[-1]], 1e-12) / np.maximum(vs[names[-2]], 1e-12))
        lim = max(float(np.abs(ratio).max()), 1e-3)
        ax = axes[r, -1]
        rs = ax.contourf(lat * 100, ax_z * 100, ratio, levels=np.linspace(-lim, lim, 21), cmap="RdBu_r")
        ax.plot(0, 0, "*", color="k", ms=11)
        ax.set_aspect("equal")
        ax.set_title(f"log2 V ratio: {names[-1]} over\n{names[-2]} ({label}-z slice)", fontsize=9)
        ax.set_xlabel(f"{label} - {label}_ref (cm)")
        fig.colorbar(rs, ax=ax, shrink=0.8, label="log2 ratio")
    fig.suptitle(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    """Command line: flow distances of the runs (JSON) and the landscape picture of the first."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, help="landscape picture (PNG) of the first run")
    ap.add_argument("--json", type=Path, help="write the flow distances here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    result = {}
    first = None
    for run in args.runs:
        cfg, policy = load_policy(run)
        first = first or (cfg, policy, run)
        result[str(run)] = flow_distance(policy) | {
            "stiffness": np.diag(policy.gains()[0].detach().numpy()).tolist(),
            "damping": np.diag(policy.gains()[1].detach().numpy()).tolist()}
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    if args.out and first is not None:
        cfg, policy, run = first
        prior = identity_flow_copy(policy, stiffness=cfg.stiffness_matrix())
        cols = {"prior (S0, identity flow)": prior,
                "learned S, D, flow reset to identity": identity_flow_copy(policy),
                "learned flow + S, D": policy}
        plot_landscape(cols, args.out, f"{cfg.task}, {run.name}: potential V(x, xdot=0) around the goal")


if __name__ == "__main__":
    main()
