"""The RealNVP flow: torch flow (learning) and compiled evaluator (1 kHz loop) are one function.

Bijectivity, the analytic Jacobian against finite differences and autograd, full rank for
any weights, torch == numba to 1e-9, the policy's controller law, log-probabilities, the
parameters round trip and gradients through J.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal

from learner_node.analysis.selfcheck import main as selfcheck_main
from learner_node.flow import RealNVPFlow, init_flow_weights
from learner_node.policy import NFPolicy
from nf_controller_node import flow_eval
from nf_controller_node.flow_eval import FlowEvaluator, pack
from nf_core.flow_spec import ACTIVATIONS, FlowArchitecture
from nf_core.policy_params import PolicyParameters

CASES = [(dim, act) for dim in (2, 3) for act in ACTIVATIONS]


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: intra-op threads only add spin-waiting on these shared 2-core machines."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _arch(dim: int, act: str, n_flow: int = 2, n_hidden: int = 8) -> FlowArchitecture:
    return FlowArchitecture(dim=dim, n_flow=n_flow, n_hidden=n_hidden, activation=act)


def _flow(arch: FlowArchitecture, seed: int = 0, scale: float = 1.0) -> RealNVPFlow:
    return RealNVPFlow(arch, init_flow_weights(arch, np.random.default_rng(seed), scale))


def _spd(rng: np.random.Generator, dim: int) -> np.ndarray:
    a = rng.normal(size=(dim, dim))
    return a @ a.T + 0.5 * np.eye(dim)


def _policy(arch: FlowArchitecture, seed: int = 0, scale: float = 1.0, sigma: float = 1.5) -> NFPolicy:
    rng = np.random.default_rng(seed)
    return NFPolicy(
        arch,
        weights=init_flow_weights(arch, rng, scale),
        stiffness=_spd(rng, arch.dim),
        damping=_spd(rng, arch.dim),
        x_ref=rng.normal(scale=0.3, size=arch.dim),
        sigma_init=sigma,
    )


def _states(dim: int, n: int, seed: int = 1) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).normal(size=(n, dim)))


# ---- torch flow ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("dim", "act"), CASES)
@pytest.mark.parametrize("scale", [1.0, 5.0])
def test_inverse_undoes_phi(dim, act, scale):
    flow = _flow(_arch(dim, act), seed=3, scale=scale)
    x = _states(dim, 64)
    with torch.no_grad():
        y = flow(x)
        back = flow.inverse(y)
    # the inverse subtracts t(c), of the size of phi: allow for that size with large weights
    tol = 1e-10 * max(1.0, float(y.abs().max())) if scale > 1 else 1e-10
    assert float((back - x).abs().max()) < tol
    assert float((y - x).abs().max()) > 1e-3  # not the identity


def test_flat_round_trip_and_layout():
    arch = _arch(3, "gelu", n_hidden=5)
    w = init_flow_weights(arch, np.random.default_rng(0))
    flow = RealNVPFlow(arch, w)
    assert w.shape == (arch.n_params,) and w.dtype == np.float64
    np.testing.assert_array_equal(flow.to_flat(), w)
    shapes = [tuple(p.shape) for p in flow.params]
    assert shapes == arch.param_shapes()
    w2 = init_flow_weights(arch, np.random.default_rng(1))
    flow.load_flat(w2)
    np.testing.assert_array_equal(flow.to_flat(), w2)
    with pytest.raises(ValueError, match="expected"):
        flow.load_flat(w2[:-1])
    big = init_flow_weights(arch, np.random.default_rng(0), scale=5.0)
    assert np.abs(big).max() > 4 * np.abs(w).max()


@pytest.mark.parametrize(("dim", "act"), CASES)
def test_identity_init_is_the_plain_impedance_law_and_trainable(dim, act):
    arch = _arch(dim, act)
    w = init_flow_weights(arch, np.random.default_rng(4), init="identity")
    w_random = init_flow_weights(arch, np.random.default_rng(4))
    assert np.count_nonzero(w) > 0.5 * w.size  # the hidden layers stay random ...
    assert np.count_nonzero(w != w_random) < 0.5 * w.size  # ... and are the random init's
    x = _states(dim, 32)
    flow = RealNVPFlow(arch, w)
    phi, jac = flow.phi_and_jacobian(x)
    np.testing.assert_array_equal(phi.detach().numpy(), x.numpy())
    np.testing.assert_array_equal(jac.detach().numpy(), np.broadcast_to(np.eye(dim), (32, dim, dim)))
    ev = FlowEvaluator(arch, w)  # the 1 kHz evaluator agrees
    for row in x.numpy()[:4]:
        np.testing.assert_array_equal(ev.phi(row), row)
    # u = -S (x - x_ref) - D xdot exactly, for the policy built from a config's flow_init
    rng = np.random.default_rng(2)
    S, D, x_ref = _spd(rng, dim), _spd(rng, dim), rng.normal(size=dim)
    policy = NFPolicy(arch, stiffness=S, damping=D, x_ref=x_ref, seed=4, flow_init="identity")
    xdot = _states(dim, 32, seed=5)
    expected = -(x.numpy() - x_ref) @ S.T - xdot.numpy() @ D.T
    np.testing.assert_allclose(policy.mean_force(x, xdot).detach().numpy(), expected, rtol=1e-12, atol=1e-12)
    # trainable: the output layers get a gradient, and one step makes phi differ from x
    loss = policy.mean_force(x, xdot).pow(2).sum()
    loss.backward()
    grads = [p.grad for p in policy.flow.params]
    assert all(g is not None for g in grads)
    assert max(float(grads[k].abs().max()) for k in range(4, len(grads), 6)) > 1e-6  # W3 of the s/t nets
    with torch.no_grad():
        for p, g in zip(policy.flow.params, grads, strict=True):
            p -= 1e-2 * g
        assert float((policy.flow(x) - x).abs().max()) > 1e-6
    with pytest.raises(ValueError, match="flow init must be one of"):
        init_flow_weights(arch, np.random.default_rng(0), init="zeros")


@pytest.mark.parametrize(("dim", "act"), CASES)
def test_jacobian_matches_finite_differences(dim, act):
    flow = _flow(_arch(dim, act), seed=5)
    x = _states(dim, 8)
    eps = 1e-6
    with torch.no_grad():
        _, J = flow.phi_and_jacobian(x)
        cols = []
        for j in range(dim):
            dx = torch.zeros(dim, dtype=x.dtype)
            dx[j] = eps
            cols.append((flow(x + dx) - flow(x - dx)) / (2 * eps))
        J_fd = torch.stack(cols, dim=-1)
    assert float((J - J_fd).abs().max()) < 1e-7 * max(1.0, float(J.abs().max()))


@pytest.mark.parametrize(("dim", "act"), CASES)
def test_jacobian_matches_autograd(dim, act):
    flow = _flow(_arch(dim, act), seed=6, scale=2.0)
    x = _states(dim, 6)
    phi, J = flow.phi_and_jacobian(x)
    for n in range(x.shape[0]):
        J_ad = torch.func.jacrev(lambda v: flow(v.unsqueeze(0))[0])(x[n])
        torch.testing.assert_close(J[n], J_ad, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(phi, flow(x), rtol=0, atol=1e-14)


@pytest.mark.parametrize(("dim", "act"), CASES)
@pytest.mark.parametrize("scale", [1.0, 5.0])
def test_jacobian_full_rank(dim, act, scale):
    arch = _arch(dim, act)
    flow = _flow(arch, seed=7, scale=scale)
    x = _states(dim, 200, seed=2) * 3.0
    with torch.no_grad():
        _, J = flow.phi_and_jacobian(x)
    det = torch.linalg.det(J)
    # det J = exp(sum of the scales s = tanh(.)): positive, and at least exp(-n_flow * dim)
    assert bool(torch.isfinite(det).all())
    assert float(det.min()) >= math.exp(-arch.n_flow * dim) * (1 - 1e-9)
    assert float(det.max()) <= math.exp(arch.n_flow * dim) * (1 + 1e-9)


def test_gradients_reach_weights_through_jacobian():
    arch = _arch(3, "gelu")
    flow = _flow(arch, seed=8)
    x = _states(3, 5)
    _, J = flow.phi_and_jacobian(x)
    loss = (J * J).sum()  # depends on the weights only through J
    params = list(flow.params)
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    # every W1 and W2 reaches J (only the last layer's t-bias b3 cannot)
    for k, g in enumerate(grads):
        if k % 6 in (0, 2):
            assert g is not None and float(g.abs().max()) > 0, f"zero gradient for parameter array {k}"
    # the same gradient as differentiating an autograd Jacobian
    J_ad = torch.stack(
        [
            torch.autograd.functional.jacobian(lambda v: flow(v.unsqueeze(0))[0], x[n], create_graph=True)
            for n in range(x.shape[0])
        ]
    )
    torch.testing.assert_close(J, J_ad, rtol=1e-12, atol=1e-12)
    grads_ad = torch.autograd.grad((J_ad * J_ad).sum(), params, allow_unused=True)
    for p, g, g_ad in zip(params, grads, grads_ad, strict=True):
        g = torch.zeros_like(p) if g is None else g
        g_ad = torch.zeros_like(p) if g_ad is None else g_ad
        torch.testing.assert_close(g, g_ad, rtol=1e-9, atol=1e-11)


# ---- torch == compiled --------------------------------------------------------------------------


@pytest.mark.parametrize(("dim", "act"), CASES)
def test_torch_and_compiled_agree(dim, act):
    for seed, (n_flow, n_hidden, scale) in enumerate([(2, 16, 1.0), (1, 5, 1.5), (3, 8, 0.7)]):
        arch = _arch(dim, act, n_flow=n_flow, n_hidden=n_hidden)
        policy = _policy(arch, seed=seed, scale=scale)
        ev = FlowEvaluator(policy.to_params())
        x = _states(dim, 25, seed=10 + seed)
        xd = _states(dim, 25, seed=20 + seed)
        with torch.no_grad():
            phi_t, J_t = policy.flow.phi_and_jacobian(x)
            u_t = policy.mean_force(x, xd)
            V_t = policy.lyapunov_potential(x)
        for n in range(x.shape[0]):
            xn, xdn = x[n].numpy(), xd[n].numpy()
            phi_c, J_c = ev.phi_and_jacobian(xn)
            np.testing.assert_allclose(phi_c, phi_t[n].numpy(), rtol=0, atol=1e-9)
            np.testing.assert_allclose(ev.phi(xn), phi_c, rtol=0, atol=1e-15)
            np.testing.assert_allclose(J_c, J_t[n].numpy(), rtol=0, atol=1e-9)
            np.testing.assert_allclose(ev.force(xn, xdn), u_t[n].numpy(), rtol=0, atol=1e-9)
            assert ev.potential(xn) == pytest.approx(float(V_t[n]), rel=1e-12, abs=1e-9)


def test_compiled_agrees_with_large_weights():
    arch = _arch(3, "gelu", n_hidden=16)
    policy = _policy(arch, seed=4, scale=5.0)
    ev = FlowEvaluator(policy.to_params())
    x, xd = _states(3, 20, seed=3), _states(3, 20, seed=4)
    with torch.no_grad():
        phi_t, J_t = policy.flow.phi_and_jacobian(x)
        u_t = policy.mean_force(x, xd)
    for n in range(x.shape[0]):
        phi_c, J_c = ev.phi_and_jacobian(x[n].numpy())
        u_c = ev.force(x[n].numpy(), xd[n].numpy())
        for ref, val in ((phi_t[n], phi_c), (J_t[n], J_c), (u_t[n], u_c)):
            ref = ref.numpy()
            assert np.all(np.abs(val - ref) <= 1e-9 * np.maximum(1.0, np.abs(ref)))


def test_force_is_zero_at_rest_at_goal_and_potential_zero():
    policy = _policy(_arch(3, "tanh"), seed=2)
    ev = FlowEvaluator(policy.to_params())
    np.testing.assert_allclose(ev.force(ev.x_ref, np.zeros(3)), 0.0, atol=1e-12)
    assert ev.potential(ev.x_ref) == pytest.approx(0.0, abs=1e-15)
    assert ev.potential(ev.x_ref + 0.1) > 0.0


def test_pack_rejects_wrong_size():
    arch = _arch(2, "gelu")
    with pytest.raises(ValueError, match="expected"):
        pack(arch, np.zeros(arch.n_params + 1))
    blocks, layout = pack(arch, np.zeros(arch.n_params))
    assert blocks.shape[0] == 2 * arch.n_layers and layout.shape[0] == arch.n_layers


def test_evaluator_rejects_bad_input_and_reuses_buffers():
    arch = _arch(3, "gelu")
    ev = FlowEvaluator(arch, init_flow_weights(arch, np.random.default_rng(0)))
    x, xd = np.array([0.1, -0.2, 0.3]), np.zeros(3)
    with pytest.raises(ValueError, match=r"x: expected shape \(3,\), got \(2,\)"):
        ev.force(x[:2], xd)
    with pytest.raises(ValueError, match=r"xdot: expected shape \(3,\), got \(4,\)"):
        ev.force(x, np.zeros(4))
    with pytest.raises(ValueError, match="x: non-finite"):
        ev.force(np.array([0.0, np.nan, 0.0]), xd)
    with pytest.raises(ValueError, match="xdot: non-finite"):
        ev.force(x, np.array([np.inf, 0.0, 0.0]))
    with pytest.raises(ValueError, match="x: non-finite"):
        ev.potential(np.array([np.inf, 0.0, 0.0]))
    with pytest.raises(ValueError, match="x: non-finite"):
        ev.phi_and_jacobian(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="not a numeric vector"):
        ev.phi(["a", "b", "c"])
    with pytest.raises(ValueError, match="out"):
        ev.force(x, xd, out=np.zeros(2))
    # lists, float32 and strided views are accepted and give the same answer
    ref = ev.force(x, xd)
    np.testing.assert_array_equal(ev.force(x.tolist(), [0, 0, 0]), ref)
    np.testing.assert_array_equal(ev.force(np.stack([x, x], axis=1)[:, 0], xd), ref)
    np.testing.assert_allclose(ev.force(x.astype(np.float32), xd), ref, atol=1e-6)
    out = np.empty(3)
    assert ev.force(x, xd, out) is out
    np.testing.assert_array_equal(out, ref)


def test_evaluator_from_arrays_validates():
    arch = _arch(2, "gelu")
    w = init_flow_weights(arch, np.random.default_rng(0))
    with pytest.raises(ValueError, match="not positive definite"):
        FlowEvaluator(arch, w, stiffness=-np.eye(2), warmup=False)
    with pytest.raises(ValueError, match="weights: expected"):
        FlowEvaluator(arch, w[:10], warmup=False)


def test_jit_works_without_a_cache_directory(monkeypatch):
    real_njit = flow_eval.numba.njit

    def njit(*args, **kwargs):
        if kwargs.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file '<x>'")
        return real_njit(*args, **kwargs)

    monkeypatch.setattr(flow_eval.numba, "njit", njit)

    def twice(v):
        return 2 * v

    with pytest.warns(RuntimeWarning, match="caching disabled"):
        f = flow_eval._jit(twice)
    assert f(21) == 42


# ---- policy -------------------------------------------------------------------------------------


def test_mean_force_formula_and_evaluator():
    policy = _policy(_arch(3, "gelu", n_hidden=16), seed=9)
    x, xd = _states(3, 7, seed=5), _states(3, 7, seed=6)
    with torch.no_grad():
        u = policy.mean_force(x, xd)
        phi, J = policy.flow.phi_and_jacobian(x)
        e = phi - policy.flow(policy.x_ref.unsqueeze(0))
        for n in range(x.shape[0]):
            Jn = J[n]
            expect = -Jn.T @ policy.S @ e[n] - Jn.T @ policy.D @ Jn @ xd[n]
            torch.testing.assert_close(u[n], expect, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(policy.mean_force(x[0], xd[0]), u[0])
    ev = FlowEvaluator(policy.to_params())
    for n in range(x.shape[0]):
        np.testing.assert_allclose(ev.force(x[n].numpy(), xd[n].numpy()), u[n].numpy(), atol=1e-9)


@pytest.mark.parametrize("per_dim", [False, True])
def test_log_prob_matches_hand_computation(per_dim):
    arch = _arch(3, "softplus")
    policy = _policy(arch, seed=10, sigma=2.0)
    if per_dim:
        policy.log_std.data = torch.tensor([0.1, -0.3, 0.5], dtype=torch.float64)
    assert policy.log_std.shape == ((3,) if per_dim else (1,))
    x, xd = _states(3, 6, seed=7), _states(3, 6, seed=8)
    a = _states(3, 6, seed=9) * 2.0
    with torch.no_grad():
        mu = policy.mean_force(x, xd)
        sigma = torch.exp(policy.log_std).expand_as(mu)
        hand = (
            -0.5 * (((a - mu) / sigma) ** 2).sum(-1)
            - torch.log(sigma).sum(-1)
            - 0.5 * arch.dim * math.log(2 * math.pi)
        )
        lp = policy.log_prob(x, xd, a)
    assert lp.shape == (6,)
    torch.testing.assert_close(lp, hand, rtol=1e-12, atol=1e-12)
    if not per_dim:
        assert float(policy.std().detach()[0]) == pytest.approx(2.0)
    lp2 = policy.log_prob(x, xd, a).sum()
    grads = torch.autograd.grad(lp2, [policy.log_std, *policy.flow.params])
    assert float(grads[0].abs().sum()) > 0 and float(grads[1].abs().sum()) > 0


def test_params_round_trip_reproduces_outputs():
    arch = _arch(3, "gelu", n_hidden=16)
    policy = _policy(arch, seed=11, sigma=1.3)
    p = policy.to_params(version=5)
    assert isinstance(p, PolicyParameters) and p.version == 5 and p.arch == arch
    assert p.log_std.shape == (1,) and p.log_std[0] == pytest.approx(math.log(1.3))
    back = NFPolicy.from_params(p)
    x, xd = _states(3, 9, seed=12), _states(3, 9, seed=13)
    a = _states(3, 9, seed=14)
    with torch.no_grad():
        torch.testing.assert_close(back.mean_force(x, xd), policy.mean_force(x, xd), rtol=0, atol=0)
        torch.testing.assert_close(back.log_prob(x, xd, a), policy.log_prob(x, xd, a), rtol=0, atol=0)
        torch.testing.assert_close(
            back.lyapunov_potential(x), policy.lyapunov_potential(x), rtol=0, atol=0
        )
    np.testing.assert_array_equal(back.to_params(5).weights, p.weights)
    # through the message fields too (what the controller node receives)
    msg = p.fill_msg(type("Msg", (), {})())
    again = PolicyParameters.from_msg(msg)
    np.testing.assert_array_equal(again.weights, p.weights)
    ev = FlowEvaluator(again)
    np.testing.assert_allclose(ev.force(x[0].numpy(), xd[0].numpy()), policy.mean_force(x[0], xd[0]).detach())


def test_policy_gradient_reaches_flow_weights_through_jacobian():
    policy = _policy(_arch(3, "gelu"), seed=12)
    # at the goal state with x = x_ref only the damping term J^T D J xdot is non-zero
    x = policy.x_ref.expand(4, -1).clone()
    xd = _states(3, 4, seed=2)
    u = policy.mean_force(x, xd)
    (u * u).sum().backward()
    w1 = policy.flow.params[0]
    assert w1.grad is not None and float(w1.grad.abs().max()) > 0


def test_selfcheck_passes(capsys):
    argv = ["--dim", "2", "--n-flow", "1", "--n-hidden", "4", "--states", "5", "--time-calls", "50"]
    code = selfcheck_main(argv)
    out = capsys.readouterr().out
    assert code == 0, out
    assert "max |J torch - compiled|" in out and "force() per call" in out


# ---- compiled learning path (flow_kernels) == plain torch ops --------------------------------------


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest difference relative to the largest reference value (at least 1)."""
    return float((a - b).abs().max()) / max(1.0, float(b.abs().max()))


def _values_and_grads(fn, x: torch.Tensor, params: list, cotangents: list) -> list[torch.Tensor]:
    """Outputs of fn(x) and the gradient of sum(out * cotangent) in x and every parameter."""
    x = x.clone().requires_grad_()
    outs = fn(x)
    outs = outs if isinstance(outs, tuple) else (outs,)
    loss = sum((o * c).sum() for o, c in zip(outs, cotangents, strict=True))
    grads = torch.autograd.grad(loss, [x, *params], allow_unused=True)
    grads = [torch.zeros_like(p) if g is None else g for p, g in zip([x, *params], grads, strict=True)]
    return [o.detach() for o in outs] + grads


@pytest.mark.parametrize(("dim", "act"), CASES)
@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_compiled_phi_and_jacobian_equals_autograd_reference(dim, act, scale):
    flow = _flow(_arch(dim, act, n_flow=3, n_hidden=7), seed=13, scale=scale)
    assert flow.compiled()
    x = _states(dim, 17, seed=3)
    cot = [_states(dim, 17, seed=4), _states(dim * dim, 17, seed=5).reshape(17, dim, dim)]
    params = list(flow.params)
    fast = _values_and_grads(flow.phi_and_jacobian, x, params, cot)
    ref = _values_and_grads(flow.phi_and_jacobian_autograd, x, params, cot)
    for a, b in zip(fast, ref, strict=True):
        assert _rel_err(a, b) < 1e-11  # the same sums in another order
    with torch.no_grad():  # the forward-only path (nothing kept for backward) gives the same values
        phi, J = flow.phi_and_jacobian(x)
    assert torch.equal(phi, fast[0]) and torch.equal(J, fast[1])


@pytest.mark.parametrize(("dim", "act"), CASES)
def test_compiled_mean_force_equals_reference(dim, act):
    policy = _policy(_arch(dim, act, n_flow=2, n_hidden=9), seed=14, scale=2.0)
    x, xd = _states(dim, 11, seed=6), _states(dim, 11, seed=7)
    params = list(policy.flow.params)
    cot = [_states(dim, 11, seed=8)]
    fast = _values_and_grads(lambda v: policy.mean_force(v, xd), x, params, cot)
    ref = _values_and_grads(lambda v: policy.mean_force_reference(v, xd), x, params, cot)
    for a, b in zip(fast, ref, strict=True):
        assert _rel_err(a, b) < 1e-11
    # the gradient the PPO update takes: log_prob through the mean force into every weight array
    # (the last t-bias cancels in phi(x) - phi(x_ref): its gradient is 0 up to rounding in both)
    a = _states(dim, 11, seed=9)
    grads = torch.autograd.grad(policy.log_prob(x, xd, a).sum(), params)
    mean = policy.mean_force_reference(x, xd)
    grads_ref = torch.autograd.grad(Normal(mean, policy.std().expand_as(mean)).log_prob(a).sum(), params)
    flat, flat_ref = torch.cat([g.reshape(-1) for g in grads]), torch.cat([g.reshape(-1) for g in grads_ref])
    assert _rel_err(flat, flat_ref) < 1e-11


def test_compiled_path_gathers_weights_when_not_aliased_and_float32_uses_torch_ops():
    arch = _arch(3, "gelu")
    policy = _policy(arch, seed=15)
    x, xd = _states(3, 5, seed=1), _states(3, 5, seed=2)
    with torch.no_grad():
        before = policy.mean_force(x, xd)
        # replacing a parameter's storage breaks the flat-buffer aliasing: weights are gathered instead
        w1 = policy.flow.params[0]
        w1.data = w1.data.clone()
        torch.testing.assert_close(policy.mean_force(x, xd), before, rtol=0, atol=0)
        w1.add_(0.1)  # and the kernels see the new storage
        torch.testing.assert_close(policy.mean_force(x, xd), policy.mean_force_reference(x, xd), rtol=1e-12,
                                   atol=1e-12)
    p32 = NFPolicy(arch, weights=init_flow_weights(arch, np.random.default_rng(0)), dtype=torch.float32)
    assert not p32.flow.compiled()
    u32 = p32.mean_force(x.float(), xd.float())
    assert u32.dtype == torch.float32
    p64 = NFPolicy(arch, weights=init_flow_weights(arch, np.random.default_rng(0)))
    torch.testing.assert_close(u32.double(), p64.mean_force(x, xd).detach(), rtol=1e-4, atol=1e-5)


# ---- learned gains ------------------------------------------------------------------------------


def _learned_gain_policy(seed: int = 3) -> NFPolicy:
    arch = _arch(3, "gelu", n_flow=1, n_hidden=16)
    rng = np.random.default_rng(seed)
    policy = NFPolicy(arch, weights=init_flow_weights(arch, rng), stiffness=np.diag([300.0, 250.0, 60.0]),
                      damping=np.diag([40.0, 30.0, 20.0]), x_ref=rng.normal(scale=0.3, size=3), learn_gains=True)
    with torch.no_grad():  # move off the initial values, so the test sees the learned ones in use
        policy.ln_s.add_(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
        policy.ln_d.add_(torch.tensor([-0.1, 0.4, 0.2], dtype=torch.float64))
    return policy


def test_learned_gains_compiled_gradient_equals_reference():
    """The compiled mean force's S, D gradient (to ln_s, ln_d) equals plain torch autograd."""
    policy = _learned_gain_policy()
    x, xd = _states(3, 9, seed=11) * 0.2, _states(3, 9, seed=12) * 0.1
    weights = torch.from_numpy(np.random.default_rng(4).normal(size=(9, 3)))
    grads = []
    for fn in (policy.mean_force, policy.mean_force_reference):
        policy.zero_grad()
        (fn(x, xd) * weights).sum().backward()
        grads.append([p.grad.clone() for p in (policy.ln_s, policy.ln_d, *policy.flow.param_list())])
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    assert float(policy.ln_s.grad.abs().sum()) > 0.0 and float(policy.ln_d.grad.abs().sum()) > 0.0


def test_learned_gains_reach_the_compiled_evaluator():
    """The controller's evaluator (from the parameters message) uses the learned S, D: equal forces and V."""
    policy = _learned_gain_policy()
    params = policy.to_params()
    S = policy.gains()[0]
    np.testing.assert_allclose(params.stiffness, S.detach().numpy())
    np.testing.assert_allclose(np.diag(params.damping), np.exp(policy.ln_d.detach().numpy()))
    ev = FlowEvaluator(params)
    x, xd = _states(3, 6, seed=13) * 0.2, _states(3, 6, seed=14) * 0.1
    with torch.no_grad():
        u = policy.mean_force(x, xd)
        v = policy.lyapunov_potential(x)
    for n in range(x.shape[0]):
        np.testing.assert_allclose(ev.force(x[n].numpy(), xd[n].numpy()), u[n].numpy(), atol=1e-9)
        assert abs(ev.potential(x[n].numpy()) - float(v[n])) < 1e-9
    policy.sync_gains()
    torch.testing.assert_close(policy.S, S.detach())


def test_learned_gains_need_a_positive_diagonal():
    arch = _arch(3, "gelu", n_flow=1)
    with pytest.raises(ValueError, match="positive diagonal"):
        NFPolicy(arch, stiffness=_spd(np.random.default_rng(0), 3), learn_gains=True)
