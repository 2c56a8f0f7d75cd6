"""Why a flow-weight perturbation barely shapes the landscape: nonlinearity of phi around x_ref.

Perturbs every weight of the gear's identity flow (n_flow 1, 16 hidden, gelu) by sigma, in metres
(the nets see x in m) and in normalised units (``rescale_flow_weights``), 20 draws each, and prints
means of: max |J(x_ref) - I|, the non-affine part of phi over a +-3 cm box, max |J(x) - J(x_ref)|.
"""

import numpy as np
import torch

from learner_node.flow import RealNVPFlow, init_flow_weights, rescale_flow_weights
from nf_core.flow_spec import FlowArchitecture

arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=16, activation="gelu")
xr = np.array([0.5, 0.0, 0.07])
g = np.stack(np.meshgrid(*[np.linspace(-0.03, 0.03, 7)] * 3), -1).reshape(-1, 3) + xr


def stats(w: np.ndarray) -> tuple[float, float, float]:
    """(max |J(x_ref) - I|, non-affine part of phi over the box in mm, max |J(x) - J(x_ref)|)."""
    f = RealNVPFlow(arch, w)
    phi, J = f.phi_and_jacobian(torch.tensor(np.vstack([xr, g])))
    phi, J = phi.detach().numpy(), J.detach().numpy()
    lin = phi[0] + (g - xr) @ J[0].T
    return np.abs(J[0] - np.eye(3)).max(), np.abs(phi[1:] - lin).max() * 1e3, np.abs(J[1:] - J[0]).max()


rng = np.random.default_rng(1)
for name, L in (("metres (today)", 0.0), ("normalised L=0.05", 0.05), ("normalised L=0.02", 0.02)):
    for sig in (0.05, 0.3):
        res = []
        for k in range(20):
            w0 = init_flow_weights(arch, np.random.default_rng(k), init="identity")
            w = w0 + sig * rng.standard_normal(w0.size)
            res.append(stats(rescale_flow_weights(arch, w, xr, L) if L else w))
        r = np.array(res).mean(0)
        print(f"{name:20s} sigma {sig}: |J(x_ref)-I|max {r[0]:.3f}; nonlinear part of phi over +-3 cm box "
              f"{r[1]:.3f} mm; max |J(x)-J(x_ref)| {r[2]:.3f}")
