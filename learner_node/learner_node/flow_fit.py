"""Initialise a flow from demonstrated paths ("Euclideanizing flows", Rana et al. 2020).

The controller u = -J^T S e - J^T D J xdot, e = phi(x) - phi(x_ref), drives an overdamped arm along
J xdot = -D^{-1} S e: with S proportional to D the latent point moves on a straight line to
phi(x_ref). So a flow under which a demonstrated path's latent velocity J(x) v points at the latent
goal, -(phi(x) - phi(x_ref)), makes that path the controller's path (to the extent inertia, the
torque limits and contact leave it overdamped). ``fit_flow_to_demos`` finds such a flow by gradient
descent on ``1 - cos(J v, -e)`` along the demonstrations, in the learner's own architecture and in its
normalised units (``flow_input_scale``): the result is an ordinary flow, a bijection for any weights,
so the controller stays the provably stable one; only its starting landscape comes from the demo.

The demonstration is what a user gives: waypoint polylines (``demo_samples`` resamples and rounds
them), or a recorded path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.func import functional_call

from nf_core.flow_spec import FlowArchitecture

from .flow import RealNVPFlow, rescale_flow_weights


def resample_polyline(waypoints: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` m of arc length along the polyline ``waypoints`` (K, dim), ends included."""
    w = np.asarray(waypoints, dtype=np.float64)
    seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0.0:
        raise ValueError("a demonstration must move")
    keep = np.concatenate([[True], seg > 0.0])
    w, s = w[keep], s[keep]
    n = max(int(np.ceil(s[-1] / step)), 1) + 1
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, w[:, k]) for k in range(w.shape[1])], axis=1)


def demo_samples(waypoints: np.ndarray, step: float = 0.005, corner: float = 0.03,
                 end_margin: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit tangents of a demonstration given as waypoints (K, dim), in m.

    The polyline is resampled every ``step`` and its corners rounded by a moving average over about
    ``corner`` m (the ends stay put), so the tangents turn smoothly. Points closer than ``end_margin``
    to the last waypoint (the goal, where the direction to it is undefined) are dropped."""
    pts = resample_polyline(waypoints, step)
    half = max(int(round(0.5 * corner / step)), 0)
    if half:  # a centred window that shrinks towards the ends, so the ends stay put
        n = len(pts)
        pts = np.stack([pts[i - h : i + h + 1].mean(axis=0)
                        for i, h in enumerate(min(half, i, n - 1 - i) for i in range(n))])
    tangents = np.gradient(pts, axis=0)
    norm = np.linalg.norm(tangents, axis=1)
    keep = (norm > 1e-9) & (np.linalg.norm(pts - np.asarray(waypoints[-1]), axis=1) > end_margin)
    return pts[keep], tangents[keep] / norm[keep, None]


def normalised_to_physical(arch: FlowArchitecture, x_ref: np.ndarray, scale: float) -> np.ndarray:
    """The matrix of ``rescale_flow_weights`` (a linear map): physical weights = M @ normalised."""
    eye = np.eye(arch.n_params)
    return np.stack([rescale_flow_weights(arch, eye[k], x_ref, scale) for k in range(arch.n_params)], axis=1)


class _PhiJacobian(torch.nn.Module):
    """``flow.phi_and_jacobian_autograd`` as a module's forward, for ``functional_call``."""

    def __init__(self, flow: RealNVPFlow) -> None:
        super().__init__()
        self.flow = flow

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.flow.phi_and_jacobian_autograd(x)


@dataclass
class FitResult:
    """Normalised and physical weights of the fitted flow and the loss before and after the fit."""

    normalised: np.ndarray
    normalised_start: np.ndarray
    physical: np.ndarray
    loss_start: float
    loss_end: float
    mean_cosine: float


def latent_cosines(flow: RealNVPFlow, x_ref: np.ndarray, points: np.ndarray, tangents: np.ndarray,
                   rates: np.ndarray | None = None) -> np.ndarray:
    """cos of the angle between J(x) v and -R (phi(x) - phi(x_ref)) at each demo point x with tangent v
    (R = diag(``rates``), default I): 1 where the demonstration moves as the overdamped latent point does
    (with R = I: straight at the goal)."""
    with torch.no_grad():
        x = torch.as_tensor(np.asarray(points), dtype=flow.dtype)
        phi, jac = flow.phi_and_jacobian_autograd(x)
        ref = flow(torch.as_tensor(np.asarray(x_ref)[None], dtype=flow.dtype))
        v = torch.einsum("nij,nj->ni", jac, torch.as_tensor(np.asarray(tangents), dtype=flow.dtype))
        r = torch.ones(flow.arch.dim, dtype=flow.dtype) if rates is None else torch.as_tensor(rates, dtype=flow.dtype)
        return torch.nn.functional.cosine_similarity(v, r * (ref - phi), dim=1).numpy()


def fit_flow_to_demos(flow: RealNVPFlow, x_ref: np.ndarray, scale: float, points: np.ndarray,
                      tangents: np.ndarray, iterations: int = 2000, lr: float = 0.01,
                      weight_decay: float = 1e-4, rates: np.ndarray | None = None,
                      jacobian_points: np.ndarray | None = None, jacobian_weight: float = 0.0,
                      seed: int = 0) -> FitResult:
    """Fit ``flow``'s weights (in place) so that each demo point's latent velocity points along the
    overdamped latent motion -R (phi(x) - phi(x_ref)), R = diag(``rates``) = S D^{-1} (default I: at the
    latent goal, on a straight line).

    Optimised are all weights in the normalised units (the nets see (x - x_ref) / ``scale``), by Adam on
    mean(1 - cos(J v, -R e)) + ``weight_decay`` |w - w_0|^2 / n + ``jacobian_weight`` mean |J - I|_F^2
    over ``jacobian_points`` (keeps the map tame away from the demonstration), w_0 the weights the flow
    starts with. ``points``, ``tangents``: (N, dim), e.g. from ``demo_samples``."""
    arch = flow.arch
    M = torch.as_tensor(normalised_to_physical(arch, x_ref, scale))
    w0 = rescale_flow_weights(arch, flow.to_flat(), x_ref, scale, inverse=True)
    w = torch.tensor(w0, requires_grad=True)
    w0_t = torch.as_tensor(w0)
    x = torch.as_tensor(np.asarray(points), dtype=torch.float64)
    v = torch.as_tensor(np.asarray(tangents), dtype=torch.float64)
    ref = torch.as_tensor(np.asarray(x_ref), dtype=torch.float64)[None]
    rate = torch.ones(arch.dim, dtype=torch.float64) if rates is None else torch.as_tensor(rates, dtype=torch.float64)
    reg = (torch.zeros((0, arch.dim), dtype=torch.float64) if jacobian_points is None or jacobian_weight <= 0.0
           else torch.as_tensor(np.asarray(jacobian_points), dtype=torch.float64))
    n_demo = len(x)
    eye = torch.eye(arch.dim, dtype=torch.float64)
    names = [f"flow.params.{k}" for k in range(len(arch.param_shapes()))]
    sizes = [int(np.prod(s)) for s in arch.param_shapes()]
    module = _PhiJacobian(flow)
    torch.manual_seed(seed)
    opt = torch.optim.Adam([w], lr=lr)

    def loss_of(weights: torch.Tensor) -> torch.Tensor:
        phys = M @ weights
        params = {n: p.view(s) for n, p, s in zip(names, phys.split(sizes), arch.param_shapes(), strict=True)}
        phi, jac = functional_call(module, params, (torch.cat([x, ref, reg]),))
        e = phi[:n_demo] - phi[n_demo : n_demo + 1]
        lat_v = torch.einsum("nij,nj->ni", jac[:n_demo], v)
        cos = torch.nn.functional.cosine_similarity(lat_v, -rate * e, dim=1, eps=1e-12)
        loss = (1.0 - cos).mean() + weight_decay * ((weights - w0_t) ** 2).mean()
        if len(reg):
            loss = loss + jacobian_weight * ((jac[n_demo + 1 :] - eye) ** 2).sum((1, 2)).mean()
        return loss

    with torch.no_grad():
        start = float(loss_of(w))
    for _ in range(iterations):
        opt.zero_grad()
        loss = loss_of(w)
        loss.backward()
        opt.step()
    normalised = w.detach().numpy().copy()
    physical = rescale_flow_weights(arch, normalised, x_ref, scale)
    flow.load_flat(physical)
    with torch.no_grad():
        end = float(loss_of(w))
    cos = latent_cosines(flow, x_ref, points, tangents, rates)
    return FitResult(normalised, w0, physical, start, end, float(cos.mean()))


def shift_profile(n: int, centre: float, width: float = 0.2) -> np.ndarray:
    """Weights (n,) along a path of n points by arc-length fraction: a bump exp(-((s - centre) / width)^2)
    times s (1 - s) / 0.25, so a path's start and end stay where they are."""
    s = np.linspace(0.0, 1.0, n)
    return np.exp(-(((s - centre) / width) ** 2)) * s * (1.0 - s) / 0.25


SHIFT_CENTRES = (0.3, 0.6)  # arc-length fractions of the path where demo_basis moves it (early, late)


def demo_basis(flow: RealNVPFlow, x_ref: np.ndarray, scale: float, paths: list[np.ndarray], shift: float = 0.01,
               iterations: int = 60, **fit: object) -> np.ndarray:
    """Directions in the normalised flow weights (n_params, 6) along which the fitted ``flow`` changes when
    every demonstration moves: by ``shift`` m along x, y or z, around 30 % or 60 % of its length
    (``shift_profile``; start and goal stay). Each column is (refit of the moved paths) - (refit of the
    same paths), both ``iterations`` warm Adam steps from ``flow``'s weights with the same ``fit``
    settings as ``fit_flow_to_demos``, so one unit along it is the fit of demonstrations moved by ``shift``.
    ``flow`` is not changed. Exploring along these is exploring the demonstrations' space: every draw is
    still a flow, hence a stable controller."""
    import copy

    def refit(moved: list[np.ndarray]) -> np.ndarray:
        f = copy.deepcopy(flow)
        samples = [demo_samples(p) for p in moved]
        points = np.concatenate([p for p, _ in samples])
        tangents = np.concatenate([t for _, t in samples])
        return fit_flow_to_demos(f, x_ref, scale, points, tangents, iterations=iterations, **fit).normalised

    base = refit(paths)
    cols = []
    for centre in SHIFT_CENTRES:
        for axis in range(3):
            moved = []
            for p in paths:
                q = np.array(p, dtype=np.float64)
                q[:, axis] += shift * shift_profile(len(q), centre)
                moved.append(q)
            cols.append(refit(moved) - base)
    return np.stack(cols, axis=1)
