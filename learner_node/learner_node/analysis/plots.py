"""Figures of learning results (matplotlib, Agg backend, PNG files).

- ``plot_learning_curves``: return, success and final distance per iteration, mean and spread over
  seeds (one group); ``plot_learning_curve_groups`` overlays several groups (say NF-PPO vs PPO).
  Both take the metrics rows a ``Trainer`` keeps in ``history`` (one list per seed).
- ``plot_energy_landscape``: the 2-D block task's potential V(x, xdot=0) before and after learning
  with a deterministic rollout on top, and the same in the flow's latent space y = phi(x), where V is
  the quadratic 1/2 (y - y_ref)^T S (y - y_ref) (the paper's Fig. 4 c-e).
- ``plot_final_distance_distribution``: histograms of the end-effector's final distance to the goal
  (say over the episodes of the first 10 iterations), one per group.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

CURVE_KEYS = (("return_mean", "mean return"), ("success_rate", "success rate"),
              ("final_distance_mean", "final distance to goal (m)"))
_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray",
           "tab:olive", "tab:cyan")


def _pyplot():  # returns the pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def curve_stats(histories: Sequence[Sequence[Mapping[str, float]]], key: str) -> tuple[np.ndarray, ...]:
    """(iterations, mean, min, max) of metric ``key`` over seeds, up to the shortest run's length."""
    runs = [h for h in histories if h]
    if not runs:
        empty = np.zeros(0)
        return empty, empty, empty, empty
    n = min(len(h) for h in runs)
    values = np.array([[float(row[key]) for row in h[:n]] for h in runs])
    iters = np.array([float(row["iteration"]) for row in runs[0][:n]])
    return iters, values.mean(axis=0), values.min(axis=0), values.max(axis=0)


# a curve's column -> the column of the periodic deterministic evaluations (TrainConfig.eval_every)
EVAL_OF = {"return_mean": "eval_return", "success_rate": "eval_success", "final_distance_mean": "eval_final_distance"}


def periodic_evaluations(histories: Sequence[Sequence[Mapping[str, float]]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, mean over seeds) of the periodic evaluations' ``key`` column (``EVAL_OF``): the
    iterations at which every seed that reached them was evaluated; empty if none was."""
    column = EVAL_OF.get(key)
    points: dict[float, list[float]] = {}
    for h in histories:
        for row in h:
            value = float(row.get(column, math.nan)) if column else math.nan
            if math.isfinite(value):
                points.setdefault(float(row["iteration"]), []).append(value)
    its = sorted(points)
    return np.array(its), np.array([np.mean(points[i]) for i in its])


def plot_learning_curve_groups(groups: Mapping[str, Sequence[Sequence[Mapping[str, float]]]], path: str | Path,
                               title: str = "", evaluations: Sequence[tuple[str, float, Mapping[str, float]]] = ()
                               ) -> Path:
    """Return, success and final distance per iteration: per group the mean over seeds (line) and the
    range over seeds (band). ``groups`` maps a label to one metrics history per seed. ``evaluations``:
    (label, iteration, evaluation row) drawn as single points, say the deterministic controller on
    held-out starts before and after training. Writes ``path``."""
    plt = _pyplot()
    path = Path(path)
    fig, axes = plt.subplots(1, len(CURVE_KEYS), figsize=(4.2 * len(CURVE_KEYS), 3.4))
    for g, (label, histories) in enumerate(groups.items()):
        color = _COLORS[g % len(_COLORS)]
        style = "--" if g >= len(_COLORS) else "-"  # more groups than colours: dashed for the second round
        seeds = sum(1 for h in histories if h)
        for ax, (key, _) in zip(axes, CURVE_KEYS, strict=True):
            it, mean, lo, hi = curve_stats(histories, key)
            if it.size == 0:
                continue
            ax.plot(it, mean, color=color, linestyle=style, label=f"{label} ({seeds} seed{'s' if seeds != 1 else ''})")
            if seeds > 1:
                ax.fill_between(it, lo, hi, color=color, alpha=0.2, linewidth=0)
            ev_it, ev_mean = periodic_evaluations(histories, key)
            if ev_it.size:
                ax.plot(ev_it, ev_mean, linestyle="none", marker="x", markersize=7, color=color,
                        label=f"{label}: deterministic, held-out (eval_every)")
    for (label, iteration, row), marker in zip(evaluations, ("o", "*", "s", "D"), strict=False):
        for ax, (key, _) in zip(axes, CURVE_KEYS, strict=True):
            if key in row:
                ax.plot([iteration], [float(row[key])], linestyle="none", marker=marker, markersize=9,
                        color="black", label=label)
    for ax, (key, ylabel) in zip(axes, CURVE_KEYS, strict=True):
        ax.set_xlabel("iteration")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if key == "success_rate":
            ax.set_ylim(-0.05, 1.05)
    if groups or evaluations:
        axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_learning_curves(histories: Sequence[Sequence[Mapping[str, float]]], path: str | Path, title: str = "",
                         label: str = "mean over seeds",
                         evaluations: Sequence[tuple[str, float, Mapping[str, float]]] = ()) -> Path:
    """Learning curves of one configuration: ``histories`` holds each seed's ``Trainer.history``
    (a single run is ``[trainer.history]``). Mean over seeds with the min-max band; ``evaluations``
    as in ``plot_learning_curve_groups``. Writes ``path``."""
    return plot_learning_curve_groups({label: histories}, path, title, evaluations)


def evaluation_points(evaluations: Sequence[tuple[str, Mapping]]) -> list[tuple[str, float, Mapping]]:
    """``plot_learning_curves``'s ``evaluations`` from a run's (label, evaluation) pairs
    (``trainer.run_evaluations``): the prior's and the learned controller's held-out results."""
    return [(f"{'prior' if e['iteration'] == 0 else 'learned'}: held-out, deterministic", float(e["iteration"]), e)
            for _, e in evaluations]


def plot_final_distance_distribution(groups: Mapping[str, Sequence[float]], path: str | Path,
                                     title: str = "") -> Path:
    """Histogram of final end-effector distances to the goal (m), one per group, same bins. Writes ``path``."""
    plt = _pyplot()
    path = Path(path)
    data = {k: np.asarray(v, dtype=float) for k, v in groups.items() if len(v)}
    fig, ax = plt.subplots(figsize=(6, 3.6))
    if data:
        hi = max(float(v.max()) for v in data.values())
        bins = np.linspace(0.0, max(hi, 1e-3) * 1.02, 31)
        for g, (label, values) in enumerate(data.items()):
            ax.hist(values, bins=bins, alpha=0.55, color=_COLORS[g % len(_COLORS)],
                    label=f"{label}: {values.mean() * 100:.1f} ± {values.std() * 100:.1f} cm (n={values.size})")
        ax.legend(fontsize=8)
    ax.set_xlabel("final distance to goal (m)")
    ax.set_ylabel("episodes")
    ax.grid(alpha=0.3)
    ax.set_title(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------- energy landscape (2-D)
def _potential_grid(policy: object, xs: np.ndarray, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """V(x, 0) and phi(x) on the grid (len(zs), len(xs)) of a 2-D ``NFPolicy``."""
    import torch

    gx, gz = np.meshgrid(xs, zs)
    pts = torch.from_numpy(np.stack([gx.ravel(), gz.ravel()], axis=1))
    with torch.no_grad():
        v = policy.lyapunov_potential(pts).numpy().reshape(gx.shape)
        y = policy.flow(pts).numpy().reshape(*gx.shape, 2)
    return v, y


def _phi(policy: object, pts: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        return policy.flow(torch.from_numpy(np.asarray(pts, dtype=np.float64).reshape(-1, 2))).numpy()


def plot_energy_landscape(policies: Mapping[str, object], trajectories: Mapping[str, np.ndarray], path: str | Path,
                          *, x_ref: np.ndarray, extent: tuple[float, float, float, float],
                          obstacles: Sequence[np.ndarray] = (), title: str = "", grid: int = 61) -> Path:
    """Energy landscape of 2-D flow controllers (one column per entry of ``policies``, e.g. before and
    after learning): top row V(x, xdot=0) in task space (log-scaled contours) with the rollout
    ``trajectories[label]`` ((K, 2) positions) and the ``obstacles`` (polygons, (n, 2)); bottom row the
    same in the latent space y = phi(x): the quadratic V(y) = 1/2 (y - y_ref)^T S (y - y_ref), the image
    of a task-space grid, the mapped obstacles and rollout. ``extent`` = (x_min, x_max, z_min, z_max)."""
    plt = _pyplot()
    import torch

    path = Path(path)
    xs = np.linspace(extent[0], extent[1], grid)
    zs = np.linspace(extent[2], extent[3], grid)
    n = len(policies)
    fig, axes = plt.subplots(2, n, figsize=(5.0 * n, 8.6), squeeze=False)
    x_ref = np.asarray(x_ref, dtype=np.float64).reshape(2)
    for c, (label, policy) in enumerate(policies.items()):
        v, y = _potential_grid(policy, xs, zs)
        traj = trajectories.get(label)
        ax = axes[0, c]
        levels = np.geomspace(max(float(v.min()), 1e-6 * float(v.max()), 1e-12), float(v.max()), 20)
        ax.contourf(xs, zs, v, levels=levels, cmap="viridis", norm=_log_norm())
        ax.contour(xs, zs, v, levels=levels, colors="k", linewidths=0.3, alpha=0.5)
        for poly in obstacles:
            ax.fill(poly[:, 0], poly[:, 1], color="0.55", alpha=0.9)
        if traj is not None:
            ax.plot(traj[:, 0], traj[:, 1], color="w", lw=1.8)
            ax.plot(traj[0, 0], traj[0, 1], "o", color="w", ms=5)
        ax.plot(*x_ref, "*", color="r", ms=11)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_title(f"{label}: V(x, ẋ=0), task space")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        # latent space
        ax = axes[1, c]
        y_ref = _phi(policy, x_ref)[0]
        S = policy.gains()[0].detach().to(torch.float64).numpy()
        ymin, ymax = y.reshape(-1, 2).min(axis=0), y.reshape(-1, 2).max(axis=0)
        pad = 0.05 * (ymax - ymin)
        y1 = np.linspace(ymin[0] - pad[0], ymax[0] + pad[0], grid)
        y2 = np.linspace(ymin[1] - pad[1], ymax[1] + pad[1], grid)
        g1, g2 = np.meshgrid(y1, y2)
        e = np.stack([g1 - y_ref[0], g2 - y_ref[1]], axis=-1)
        vy = 0.5 * np.einsum("...i,ij,...j->...", e, S, e)
        lv = np.geomspace(max(float(vy.min()), 1e-6 * float(vy.max()), 1e-12), float(vy.max()), 20)
        ax.contourf(y1, y2, vy, levels=lv, cmap="viridis", norm=_log_norm())
        step = max(1, grid // 12)
        for i in range(0, grid, step):  # images of the task-space grid lines
            ax.plot(y[i, :, 0], y[i, :, 1], color="w", lw=0.4, alpha=0.6)
            ax.plot(y[:, i, 0], y[:, i, 1], color="w", lw=0.4, alpha=0.6)
        for poly in obstacles:
            clipped = np.clip(poly, [extent[0], extent[2]], [extent[1], extent[3]])
            dense = _densify(clipped)
            py = _phi(policy, dense)
            ax.fill(py[:, 0], py[:, 1], color="0.55", alpha=0.9)
        if traj is not None:
            ty = _phi(policy, traj)
            ax.plot(ty[:, 0], ty[:, 1], color="w", lw=1.8)
            ax.plot(ty[0, 0], ty[0, 1], "o", color="w", ms=5)
        ax.plot(*y_ref, "*", color="r", ms=11)
        ax.set_title(f"{label}: latent space y = phi(x)")
        ax.set_xlabel("y1")
        ax.set_ylabel("y2")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _log_norm():  # returns a matplotlib LogNorm
    from matplotlib.colors import LogNorm

    return LogNorm()


def _densify(poly: np.ndarray, per_edge: int = 40) -> np.ndarray:
    """A closed polygon with ``per_edge`` points on each edge (so its image under phi is drawn curved)."""
    pts = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        t = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None]
        pts.append(a + t * (b - a))
    return np.concatenate(pts)
