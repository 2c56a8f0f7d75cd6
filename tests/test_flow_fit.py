"""learner_node.flow_fit: a flow fitted to a demonstrated path maps it to a straight latent path to the goal,
and stays an invertible flow."""

from __future__ import annotations

import numpy as np
import torch

from learner_node.flow import RealNVPFlow, init_flow_weights, rescale_flow_weights
from learner_node.flow_fit import demo_samples, fit_flow_to_demos, latent_cosines, normalised_to_physical
from nf_core.flow_spec import FlowArchitecture

X_REF = np.array([0.5, 0.0, 0.07])
SCALE = 0.05


def _identity_flow(arch: FlowArchitecture) -> RealNVPFlow:
    normalised = init_flow_weights(arch, np.random.default_rng(0), init="identity")
    return RealNVPFlow(arch, weights=rescale_flow_weights(arch, normalised, X_REF, SCALE))


def test_normalised_to_physical_is_the_rescaling():
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=4, activation="gelu")
    w = np.random.default_rng(1).normal(size=arch.n_params)
    M = normalised_to_physical(arch, X_REF, SCALE)
    np.testing.assert_allclose(M @ w, rescale_flow_weights(arch, w, X_REF, SCALE), atol=1e-12)


def test_demo_samples_are_unit_tangents_that_stop_short_of_the_goal():
    wp = np.array([[0.7, 0.0, 0.12], [0.7, 0.0, 0.3], [0.5, 0.0, 0.3], X_REF])
    pts, tan = demo_samples(wp, step=0.005, corner=0.03, end_margin=0.01)
    np.testing.assert_allclose(np.linalg.norm(tan, axis=1), 1.0)
    assert np.linalg.norm(pts - X_REF, axis=1).min() > 0.01
    np.testing.assert_allclose(pts[0], wp[0])  # the ends stay put
    assert np.allclose(tan[0], [0.0, 0.0, 1.0], atol=1e-6)  # first up, ...
    assert tan[len(tan) // 2] @ np.array([-1.0, 0.0, 0.0]) > 0.99  # ... then over


def test_a_lifting_demo_becomes_a_straight_latent_path_and_the_flow_stays_invertible():
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=6, activation="gelu")
    flow = _identity_flow(arch)
    wp = np.array([[0.7, 0.0, 0.12], [0.7, 0.0, 0.3], [0.5, 0.0, 0.3], X_REF])
    pts, tan = demo_samples(wp, step=0.02)
    before = latent_cosines(flow, X_REF, pts, tan)
    assert before.mean() < 0.6  # the identity: the path goes up and sideways, not at the goal
    fit = fit_flow_to_demos(flow, X_REF, SCALE, pts, tan, iterations=80, lr=0.05)
    after = latent_cosines(flow, X_REF, pts, tan)
    assert fit.loss_end < 0.1 * fit.loss_start
    assert after.mean() > 0.97 and np.percentile(after, 10) > 0.9
    np.testing.assert_allclose(flow.to_flat(), fit.physical)
    # the latent images of the demo lie close to the segment from phi(start) to phi(x_ref)
    with torch.no_grad():
        lat = flow(torch.as_tensor(pts)).numpy()
        ref = flow(torch.as_tensor(X_REF[None])).numpy()[0]
        back = flow.inverse(torch.as_tensor(lat)).numpy()
    np.testing.assert_allclose(back, pts, atol=1e-9)  # still a bijection
    d = ref - lat[0]
    rel = lat - lat[0]
    off_line = np.linalg.norm(rel - np.outer(rel @ d / (d @ d), d), axis=1)
    assert off_line.max() < 0.15 * np.linalg.norm(d)
