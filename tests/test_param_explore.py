"""Parameter-space exploration: mirrored draws, controller parameters of a draw, the PPO update, the
trainer's params mode, and the free-space stability measurement."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from learner_node.analysis.exploration_stability import measure, summarize
from learner_node.config import TrainConfig
from learner_node.flow import RealNVPFlow, init_flow_weights, output_layer_mask, rescale_flow_weights
from learner_node.param_explore import ParamExploration, paired_advantages
from learner_node.param_ppo import make_param_optimizer, param_ppo_update
from learner_node.policy import NFPolicy
from learner_node.spread import settle_factor
from learner_node.trainer import CHECKPOINT, Trainer
from nf_core.flow_spec import FlowArchitecture

TINY = {"task": "block", "iterations": 2, "rollouts_per_iter": 5, "episode_seconds": 0.2, "update_epochs": 3,
        "eval_episodes": 1, "gains": "learned", "exploration": "params", "flow_init": "identity"}


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _policy(flow_sigma: float = 0.0) -> tuple[NFPolicy, ParamExploration]:
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=8, activation="gelu")
    policy = NFPolicy(arch, stiffness=np.diag([300.0, 300.0, 300.0]), damping=np.diag([40.0] * 3),
                      x_ref=np.array([0.5, 0.0, 0.3]), learn_gains=True, flow_init="identity")
    return policy, ParamExploration(policy, 0.4, flow_sigma)


def test_mirrored_draws_and_their_controller_parameters():
    _, explorer = _policy(flow_sigma=0.01)
    theta, eps = explorer.sample(7, np.random.default_rng(0))
    assert theta.shape == (7, 6 + explorer.n_flow)  # ln S, ln D, and the flow's fixed directions
    np.testing.assert_array_equal(eps[0::2][:3], -eps[1::2])  # pairs mu +- sigma eps
    np.testing.assert_array_equal(eps[6], 0.0)  # odd last: mu itself
    mu = explorer.mean().detach().numpy()
    np.testing.assert_allclose(theta[6], mu)
    p = explorer.params_for(theta[0])
    np.testing.assert_allclose(np.diag(p.stiffness), np.exp(theta[0, :3]))
    np.testing.assert_allclose(np.diag(p.damping), np.exp(theta[0, 3:6]))
    np.testing.assert_allclose(p.weights, explorer.flow_weights(theta[0, 6:]))
    assert np.all(np.linalg.eigvalsh(p.stiffness) > 0) and np.all(np.linalg.eigvalsh(p.damping) > 0)


def test_decay_scales_every_std():
    _, explorer = _policy(flow_sigma=0.01)
    before = explorer.sigma().detach().clone()
    explorer.decay(0.5)
    torch.testing.assert_close(explorer.sigma().detach(), 0.5 * before)


def test_paired_advantages():
    adv = paired_advantages(np.array([3.0, 1.0, 0.0, 4.0, 9.0]))
    np.testing.assert_allclose(adv / adv[0], [1.0, -1.0, -2.0, 2.0, 0.0])
    assert abs(np.sqrt(np.mean(adv[:4] ** 2)) - 1.0) < 1e-12
    adv = paired_advantages(np.array([3.0, np.nan, 0.0, 4.0]))  # a failed episode drops its pair
    np.testing.assert_allclose(adv, [0.0, 0.0, -np.sqrt(2.0), np.sqrt(2.0)])


def test_update_moves_the_gains_toward_the_better_draws():
    """Rollouts return more for a softer z axis: the update lowers ln S_z and leaves the stds finite."""
    policy, explorer = _policy()
    opt = make_param_optimizer(explorer, 0.1, 0.01)
    rng = np.random.default_rng(1)
    z0 = float(policy.ln_s[2].detach())
    for _ in range(5):
        theta, _ = explorer.sample(14, rng)
        adv = paired_advantages(-theta[:, 2])
        stats = param_ppo_update(explorer, opt, theta, adv, epochs=5, clip_coef=0.2)
        assert np.isfinite(stats["approx_kl"])
    assert float(policy.ln_s[2].detach()) < z0 - 0.2
    torch.testing.assert_close(policy.S, policy.gains()[0].detach())  # synced for the checkpoint


def test_trainer_params_mode_pairs_starts_and_resumes_exactly(tmp_path):
    straight = Trainer(TrainConfig(**TINY), tmp_path / "a")
    plan = straight.episode_plan()
    assert [s for s, _, _ in plan][0::2][:2] == [s for s, _, _ in plan][1::2]  # a pair shares its start
    assert all(p is not None for _, _, p in plan)
    straight = Trainer(TrainConfig(**TINY), tmp_path / "a")
    straight.run(evaluate=False)
    assert "stiffness_1" in straight.history[-1] and "param_sigma_gains" in straight.history[-1]
    first = Trainer(TrainConfig(**{**TINY, "iterations": 1}), tmp_path / "b")
    first.run(evaluate=False)
    resumed = Trainer(TrainConfig(**TINY), tmp_path / "b")
    resumed.load_checkpoint(tmp_path / "b" / CHECKPOINT)
    resumed.run(evaluate=False)
    for key, value in straight.policy.state_dict().items():
        assert torch.equal(value, resumed.policy.state_dict()[key]), key
    assert torch.equal(straight.explorer.log_sigma_gains, resumed.explorer.log_sigma_gains)


def test_params_mode_needs_something_to_explore():
    with pytest.raises(ValueError, match="needs something to explore"):
        TrainConfig(task="block", exploration="params")


def test_free_space_parameter_draws_never_raise_v_and_action_noise_does_work():
    policy, explorer = _policy()
    params = measure(policy, "params", 4, 0.3, explorer=explorer)
    noise = measure(policy, "action", 2, 0.3, sigma=5.0, hold=0.01)
    summary = summarize(params)
    assert summary["rising_fraction"] == 0.0 and summary["rising_clamped_fraction"] == 0.0
    assert all(r.gain <= 1e-3 for r in params)
    # the limit kinds split the limited milliseconds; the records keep every rollout
    assert all(max(r.clamped_ms, r.rate_limited_ms) <= r.limited_ms <= r.clamped_ms + r.rate_limited_ms
               and r.v_max >= r.v0 for r in params + noise)
    assert [row["start_seed"] for row in summary["per_rollout"]] == [r.start_seed for r in params]
    assert any(abs(r.work) > 1e-6 for r in noise)


def test_normalised_flow_weights_are_the_same_bijection_in_metres():
    """Physical weights from normalised ones: phi_p(x) = L phi_n'(x / L), the nets seeing (c - c_ref) / L."""
    arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=8, activation="gelu")
    rng = np.random.default_rng(0)
    wn = init_flow_weights(arch, rng)
    x_ref, scale = np.array([0.5, 0.0, 0.07]), 0.05
    wp = rescale_flow_weights(arch, wn, x_ref, scale)
    np.testing.assert_allclose(rescale_flow_weights(arch, wp, x_ref, scale, inverse=True), wn, atol=1e-14)
    x = x_ref + 0.1 * rng.standard_normal((6, 3))
    a = RealNVPFlow(arch, wp)(torch.from_numpy(x)).detach().numpy()
    b = scale * RealNVPFlow(arch, rescale_flow_weights(arch, wn, x_ref / scale, 1.0))(
        torch.from_numpy(x / scale)).detach().numpy()
    np.testing.assert_allclose(a, b, atol=1e-13)
    mask = output_layer_mask(arch)
    assert mask.sum() == 2 * 2 * (8 * 2 + 2 + 8 * 1 + 1)  # per element: s and t nets of both layers
    np.testing.assert_array_equal(init_flow_weights(arch, rng, init="identity")[mask], 0.0)


def test_subspace_exploration_moves_the_output_layers_along_fixed_directions():
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=8, activation="gelu")
    x_ref = np.array([0.5, 0.0, 0.07])
    wn = init_flow_weights(arch, np.random.default_rng(3), init="identity")
    policy = NFPolicy(arch, weights=rescale_flow_weights(arch, wn, x_ref, 0.05), stiffness=np.diag([300.0] * 3),
                      damping=np.diag([40.0] * 3), x_ref=x_ref, learn_gains=True)
    explorer = ParamExploration(policy, 0.4, 0.1, flow_scale=0.05, flow_dim=4, seed=7)
    assert explorer.dim == 6 + 4
    basis = explorer.flow_basis.numpy()
    np.testing.assert_allclose(np.linalg.norm(basis, axis=0), 1.0)
    z = np.array([0.1, -0.2, 0.0, 0.3])
    full = wn.copy()
    mask = output_layer_mask(arch)
    full[mask] += basis @ z
    np.testing.assert_allclose(explorer.flow_weights(z), rescale_flow_weights(arch, full, x_ref, 0.05))
    again = ParamExploration(policy, 0.4, 0.1, flow_scale=0.05, flow_dim=4, seed=7)
    torch.testing.assert_close(again.flow_basis, explorer.flow_basis)  # from the seed: resumes the same


def test_running_advantage_scale_shrinks_small_differences():
    """param_adv_scale=running: an iteration whose pairs differ 10x less than the earlier ones steps less."""
    _, explorer = _policy()
    returns = np.array([0.0, 100.0, 50.0, -50.0])
    big = paired_advantages(returns, normalize=False)
    np.testing.assert_allclose(big / explorer.running_scale(big), paired_advantages(returns))
    small = paired_advantages(np.array([0.0, 10.0, 5.0, -5.0]), normalize=False)
    scaled = small / explorer.running_scale(small)
    rms_big = np.sqrt(np.mean(big[0::2] ** 2))
    np.testing.assert_allclose(scaled, small / ((rms_big + rms_big / 10) / 2))
    assert np.sqrt(np.mean(scaled[0::2] ** 2)) < 0.2
    state = explorer.state_dict()
    assert float(state["adv_rms_count"]) == 2.0  # in the checkpoint: a resumed run scales the same


def _outcomes(draws: list[bool], mean: bool | None) -> list:
    """Episodes as the settle rule sees them: success flags of the draws, then the mean's rollout."""
    from types import SimpleNamespace
    return [SimpleNamespace(final_success=s) for s in draws] + [None if mean is None else SimpleNamespace(
        final_success=mean)]


def test_spread_settles_only_once_the_mean_succeeds_and_the_draws_do_not(tmp_path):
    trainer = Trainer(TrainConfig(**{**TINY, "param_sigma_settle": 0.8}), tmp_path)
    assert settle_factor(trainer.cfg, _outcomes([True, False, True, False], mean=True)) == 0.8  # spread fails
    assert settle_factor(trainer.cfg, _outcomes([True, True, True, True], mean=True)) == 1.0  # draws succeed
    assert settle_factor(trainer.cfg, _outcomes([False] * 4, mean=False)) == 1.0  # the mean has not arrived
    assert settle_factor(trainer.cfg, _outcomes([True, False, False, False], mean=None)) == 1.0  # its rollout failed
    off = Trainer(TrainConfig(**TINY), tmp_path / "off")
    assert settle_factor(off.cfg, _outcomes([False] * 4, mean=True)) == 1.0  # off by default
    fixed = Trainer(TrainConfig(**{**TINY, "param_sigma_settle": 0.8, "param_sigma_lr": 0.0}), tmp_path / "fixed")
    before = fixed.explorer.sigma().detach().clone()
    fixed.run(evaluate=False)
    settled = [row["param_settled"] for row in fixed.history]
    assert len(settled) == 2 and set(settled) <= {0.0, 1.0}
    torch.testing.assert_close(fixed.explorer.sigma().detach(), before * 0.8 ** sum(settled))  # only when flagged


def test_batch_rule_settles_once_most_rollouts_succeed_and_not_all(tmp_path):
    """param_settle_rule=batch (random starts): the whole batch's success rate decides, not the mean's rollout."""
    trainer = Trainer(TrainConfig(**{**TINY, "param_sigma_settle": 0.8, "param_settle_rule": "batch",
                                     "param_settle_from": 0.6}), tmp_path)
    assert settle_factor(trainer.cfg, _outcomes([True, True, True, False], mean=False)) == 0.8  # 3 of 5
    assert settle_factor(trainer.cfg, _outcomes([True, False, False, False], mean=True)) == 1.0  # 2 of 5: not yet
    assert settle_factor(trainer.cfg, _outcomes([True] * 4, mean=True)) == 1.0  # every rollout inserts
    assert settle_factor(trainer.cfg, _outcomes([True, True, True], mean=None)) == 1.0  # 3 of 3 that ran
    assert settle_factor(trainer.cfg, _outcomes([True, False, True], mean=None)) == 0.8  # 2 of 3 that ran
    with pytest.raises(ValueError, match="param_settle_rule"):
        TrainConfig(**{**TINY, "param_settle_rule": "median"})
    with pytest.raises(ValueError, match="param_settle_from"):
        TrainConfig(**{**TINY, "param_settle_from": 1.5})


def test_settling_needs_the_mean_rollout():
    with pytest.raises(ValueError, match="odd rollouts_per_iter"):
        TrainConfig(**{**TINY, "rollouts_per_iter": 4, "param_sigma_settle": 0.8})
    # the batch rule reads every rollout's outcome, not the mean's: an even batch is fine
    even = Trainer(TrainConfig(**{**TINY, "rollouts_per_iter": 4, "param_sigma_settle": 0.8,
                                  "param_settle_rule": "batch", "param_settle_from": 0.5}))
    assert settle_factor(even.cfg, _outcomes([True, False, True], mean=False)) == 0.8  # 2 of 4 rollouts inserted
    with pytest.raises(ValueError, match="param_sigma_settle"):
        TrainConfig(**{**TINY, "param_sigma_settle": 0.0})


def test_jump_onto_succeeded_rollouts_narrows_the_spread_and_a_jump_by_return_does_not(tmp_path):
    """param_sigma_jump: the stds shrink by its factor when the elite step lands on rollouts that inserted."""
    from types import SimpleNamespace
    trainer = Trainer(TrainConfig(**{**TINY, "param_elite": "minority_returns", "param_sigma_jump": 0.3,
                                     "rollouts_per_iter": 9}), tmp_path)
    ex = trainer.explorer
    trainer.update_rule.pending, _ = ex.sample(9, np.random.default_rng(6))
    sigma = ex.sigma().detach().clone()

    def eps(won=()):
        return [SimpleNamespace(final_success=i in won, episode_return=float(i)) for i in range(8)] + [
            SimpleNamespace(final_success=False, episode_return=-1.0)]

    assert trainer.update_rule.elite_step(eps()) == 2  # by return: the spread stays
    torch.testing.assert_close(ex.sigma().detach(), sigma)
    assert trainer.update_rule.elite_step(eps(won=(2, 5))) == 2  # onto two that inserted: narrowed once
    torch.testing.assert_close(ex.sigma().detach(), sigma * 0.3)
    assert trainer.update_rule.elite_step(eps(won=tuple(range(6)))) == 0  # most inserted: no step, no narrowing
    torch.testing.assert_close(ex.sigma().detach(), sigma * 0.3)
    with pytest.raises(ValueError, match="param_sigma_jump"):
        TrainConfig(**{**TINY, "param_sigma_jump": 0.0})


def test_minority_with_returns_jumps_by_return_only_while_nothing_inserts(tmp_path):
    from types import SimpleNamespace
    trainer = Trainer(TrainConfig(**{**TINY, "param_elite": "minority_returns", "rollouts_per_iter": 9}), tmp_path)
    ex = trainer.explorer
    theta, _ = ex.sample(9, np.random.default_rng(6))
    trainer.update_rule.pending = theta

    def eps(returns, mean_return, won=()):
        return [SimpleNamespace(final_success=i in won, episode_return=r) for i, r in enumerate(returns)] + [
            SimpleNamespace(final_success=False, episode_return=mean_return)]

    returns = [-5, -1, -9, -2, -7, -8, -6, -4]
    assert trainer.update_rule.elite_step(eps(returns, -1.5)) == 0  # -2 of the best quarter does not beat the mean
    assert trainer.update_rule.elite_step(eps(returns, -3.0)) == 2  # none inserted: the best quarter by return
    np.testing.assert_allclose(ex.mean().detach().numpy(), 0.5 * (theta[1] + theta[3]))
    assert trainer.update_rule.elite_step(eps(returns, -3.0, won=(6,))) == 1  # one inserted: it wins over any return
    np.testing.assert_allclose(ex.mean().detach().numpy(), theta[6])
