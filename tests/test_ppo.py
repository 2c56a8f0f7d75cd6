"""PPO pieces against hand-computed cases; the MLP policy's compiled evaluator against its torch module."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from learner_node.mlp_policy import MLPEvaluator, MLPPolicy
from learner_node.ppo import (
    LinearFeatureBaseline,
    PPOBatch,
    PPOSettings,
    approx_kl,
    clipped_surrogate_loss,
    compute_gae,
    discounted_returns,
    normalize_advantages,
    ppo_update,
)
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: intra-op threads only add spin-waiting on these shared 2-core machines."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# ---- returns and GAE ------------------------------------------------------------------------------


def test_discounted_returns_restart_at_episode_ends():
    # episodes [1, 2, 3] and [4, 5], gamma 0.5
    g = discounted_returns([1.0, 2.0, 3.0, 4.0, 5.0], [False, False, True, False, True], 0.5)
    np.testing.assert_allclose(g, [2.75, 3.5, 3.0, 6.5, 5.0], rtol=0, atol=1e-15)


def test_gae_hand_computed_two_episodes():
    rewards, values, dones = [1.0, 2.0, 3.0], [0.5, 1.0, 2.0], [False, True, True]
    adv, ret = compute_gae(rewards, values, dones, gamma=0.9, lam=0.8)
    # episode 1: delta_1 = 2 - 1 = 1, delta_0 = 1 + 0.9 * 1 - 0.5 = 1.4, A_0 = 1.4 + 0.72 * 1
    # episode 2: delta = 3 - 2 = 1 (nothing leaks across the episode boundary)
    np.testing.assert_allclose(adv, [2.12, 1.0, 1.0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(ret, [2.62, 2.0, 3.0], rtol=0, atol=1e-14)


def test_gae_bootstraps_truncated_episode():
    adv, _ = compute_gae([1.0, 2.0, 3.0], [0.5, 1.0, 2.0], [False, True, True], 0.9, 0.8,
                         bootstrap=np.array([0.0, 10.0, 0.0]))
    # delta_1 = 2 + 0.9 * 10 - 1 = 10, A_0 = 1.4 + 0.72 * 10
    np.testing.assert_allclose(adv, [8.6, 10.0, 1.0], rtol=0, atol=1e-13)


def test_gae_limits_lambda_one_and_zero():
    rng = np.random.default_rng(0)
    r, v = rng.normal(size=12), rng.normal(size=12)
    dones = np.zeros(12, dtype=bool)
    dones[[4, 11]] = True
    adv1, ret1 = compute_gae(r, v, dones, 0.95, 1.0)
    np.testing.assert_allclose(ret1, discounted_returns(r, dones, 0.95), atol=1e-12)  # Monte Carlo
    adv0, _ = compute_gae(r, v, dones, 0.95, 0.0)
    next_v = np.append(v[1:], 0.0) * ~dones
    np.testing.assert_allclose(adv0, r + 0.95 * next_v - v, atol=1e-12)  # one-step TD error
    assert np.allclose(adv1, ret1 - v)


def test_gae_rejects_batch_not_ending_an_episode():
    with pytest.raises(ValueError, match="episode end"):
        compute_gae([1.0, 2.0], [0.0, 0.0], [True, False], 0.9, 0.9)


def test_normalize_advantages_standardises_over_the_batch():
    a = np.array([1.0, 2.0, 3.0, 6.0])
    s = normalize_advantages(a)
    assert abs(s.mean()) < 1e-15 and abs(s.std() - 1.0) < 1e-6


# ---- losses ---------------------------------------------------------------------------------------


def test_clipped_surrogate_loss_hand_computed():
    ratios = torch.tensor([1.5, 0.5, 1.1, 0.7], dtype=torch.float64)
    new_lp = torch.log(ratios).requires_grad_(True)
    old_lp = torch.zeros(4, dtype=torch.float64)
    adv = torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=torch.float64)
    loss, clip_frac = clipped_surrogate_loss(new_lp, old_lp, adv, 0.2)
    # min(rA, clip(r)A): 1.2 (clipped), 0.5, -1.1, -0.8 (clipped); loss = -mean
    assert float(loss.detach()) == pytest.approx(0.05, abs=1e-15)
    assert float(clip_frac) == pytest.approx(0.75)  # |r - 1| > 0.2 for 1.5, 0.5, 0.7
    loss.backward()
    # d loss / d log r_i = -r_i A_i / 4 where the unclipped term is active, else 0
    np.testing.assert_allclose(new_lp.grad.numpy(), [0.0, -0.125, 0.275, 0.0], atol=1e-15)


def test_approx_kl_estimator():
    lp = torch.tensor([-1.0, -2.0], dtype=torch.float64)
    assert float(approx_kl(lp, lp)) == 0.0
    value = float(approx_kl(lp + math.log(2.0), lp))
    assert value == pytest.approx(1.0 - math.log(2.0), abs=1e-15)  # (r - 1) - log r at r = 2


# ---- baselines ------------------------------------------------------------------------------------


def test_linear_baseline_fits_a_function_in_its_span():
    rng = np.random.default_rng(1)
    obs, t = rng.normal(size=(200, 4)), rng.uniform(0.0, 5.0, 200)
    true = LinearFeatureBaseline.features(obs, t) @ rng.normal(size=12)
    base = LinearFeatureBaseline()
    np.testing.assert_array_equal(base.predict(obs, t), np.zeros(200))  # unfitted: zero
    base.fit(obs, t, true)
    np.testing.assert_allclose(base.predict(obs, t), true, atol=1e-5)
    other = LinearFeatureBaseline()
    other.load_state_dict(base.state_dict())
    np.testing.assert_array_equal(other.predict(obs, t), base.predict(obs, t))


# ---- the update -----------------------------------------------------------------------------------


def _toy_batch(policy: MLPPolicy, n: int = 256) -> PPOBatch:
    """Actions from the policy; advantage +1 where the first action component is above the mean."""
    rng = np.random.default_rng(2)
    x = torch.from_numpy(rng.normal(scale=0.05, size=(n, 2)))
    xdot = torch.from_numpy(rng.normal(scale=0.1, size=(n, 2)))
    with torch.no_grad():
        mean = policy.mean_force(x, xdot)
        action = mean + policy.std() * torch.from_numpy(rng.standard_normal((n, 2)))
        old_lp = policy.log_prob(x, xdot, action)
    adv = torch.where(action[:, 0] > mean[:, 0], 1.0, -1.0).to(torch.float64)
    return PPOBatch(x, xdot, action, old_lp, adv, torch.zeros(n, dtype=torch.float64))


def test_ppo_update_moves_the_mean_toward_good_actions():
    policy = MLPPolicy(2, 16, sigma_init=1.0, seed=0)
    batch = _toy_batch(policy)
    with torch.no_grad():
        before = policy.mean_force(batch.x, batch.xdot)[:, 0].mean()
    opt = torch.optim.Adam(policy.parameters(), lr=1e-2)
    stats = ppo_update(policy, opt, batch, PPOSettings(update_epochs=4, minibatch_size=64), np.random.default_rng(0))
    with torch.no_grad():
        after = policy.mean_force(batch.x, batch.xdot)[:, 0].mean()
    assert float(after) > float(before) + 0.05
    assert stats["epochs"] == 4 and stats["approx_kl"] > 0.0 and 0.0 <= stats["clip_frac"] <= 1.0
    assert math.isnan(stats["v_loss"])


def test_ppo_update_stops_at_target_kl():
    policy = MLPPolicy(2, 16, sigma_init=1.0, seed=0)
    opt = torch.optim.Adam(policy.parameters(), lr=1e-2)
    settings = PPOSettings(update_epochs=10, minibatch_size=64, target_kl=1e-12)
    stats = ppo_update(policy, opt, _toy_batch(policy), settings, np.random.default_rng(0))
    assert stats["epochs"] == 1


def test_target_kl_stops_within_an_epoch_before_a_runaway_step():
    """A step size that blows the policy up within one epoch: the minibatch check stops it there."""
    def update(target_kl: float) -> dict[str, float]:
        policy = MLPPolicy(2, 16, sigma_init=0.3, seed=0)
        opt = torch.optim.Adam(policy.parameters(), lr=0.1)
        settings = PPOSettings(update_epochs=3, minibatch_size=16, target_kl=target_kl)
        return ppo_update(policy, opt, _toy_batch(policy), settings, np.random.default_rng(0))

    free, limited = update(0.0), update(0.01)
    assert free["epochs"] == 3 and free["approx_kl"] > 1.0
    assert limited["epochs"] == 1 and limited["approx_kl"] < 0.1 * free["approx_kl"]


# ---- MLP policy: torch module == compiled evaluator ------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("activation", ["tanh", "gelu"])
def test_mlp_evaluator_equals_torch_module(dim, activation):
    rng = np.random.default_rng(3)
    policy = MLPPolicy(dim, 16, activation, x_ref=rng.normal(size=dim), sigma_init=2.0, seed=4)
    with torch.no_grad():  # larger weights than the init, so every layer matters
        for p in policy.parameters():
            p.copy_(torch.from_numpy(rng.normal(scale=0.8, size=tuple(p.shape))))
    ev = MLPEvaluator.from_policy(policy)
    X, XD = rng.normal(scale=0.3, size=(100, dim)), rng.normal(size=(100, dim))
    with torch.no_grad():
        ref = policy.mean_force(torch.from_numpy(X), torch.from_numpy(XD)).numpy()
    out = np.empty(dim)
    got = np.array([ev.force(X[i], XD[i], out).copy() for i in range(100)])
    assert np.abs(ref).max() > 0.5
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert math.isnan(ev.potential(X[0]))


def test_mlp_evaluator_rejects_bad_input():
    ev = MLPEvaluator.from_policy(MLPPolicy(3, 8, seed=0))
    with pytest.raises(ValueError, match="not finite"):
        ev.force(np.array([np.nan, 0.0, 0.0]), np.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        ev.force(np.zeros(2), np.zeros(3))


def test_mlp_initial_mean_is_small_and_log_prob_matches_normal():
    policy = MLPPolicy(3, 64, sigma_init=2.0, seed=0)
    x = torch.zeros(5, 3, dtype=torch.float64)
    with torch.no_grad():
        assert float(policy.mean_force(x, x).abs().max()) < 0.05  # output layer scaled down
        a = torch.ones(5, 3, dtype=torch.float64)
        mean = policy.mean_force(x, x)
        ref = torch.distributions.Normal(mean, 2.0).log_prob(a).sum(-1)
        torch.testing.assert_close(policy.log_prob(x, x, a), ref)


def test_flow_controller_runs_mlp_evaluator_unchanged():
    arm = ArmModel()
    policy = MLPPolicy(3, 8, x_ref=np.array([0.5, 0.0, 0.07]), seed=1)
    ev = MLPEvaluator.from_policy(policy)
    ctrl = FlowController(arm, ev)
    q = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])
    dq = np.full(7, 0.05)
    tau = ctrl.step(q, dq, np.array([1.0, -2.0, 0.5]))
    assert np.all(np.isfinite(tau)) and not ctrl.fault
    np.testing.assert_allclose(ctrl.u, ev.force(arm.x, ctrl.xdot) + [1.0, -2.0, 0.5], atol=1e-12)
