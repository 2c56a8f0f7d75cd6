"""The bounded potential pull (FlowEvaluator.set_force_bound, TorqueLawConfig.potential_force_bound):
still the gradient of a potential, never above the bound, the plain law without it."""

from __future__ import annotations

import numpy as np
import pytest

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters

X_REF = np.array([0.5, 0.0, 0.07])
S = np.array([[1500.0, 100.0, 0.0], [100.0, 700.0, 0.0], [0.0, 0.0, 200.0]])


def _evaluator(identity: bool = False, damping: float = 1e-9) -> FlowEvaluator:
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=8, activation="gelu")
    weights = np.zeros(arch.n_params) if identity else np.random.default_rng(3).uniform(-0.3, 0.3, arch.n_params)
    return FlowEvaluator(PolicyParameters(arch, weights, np.zeros(1), S, damping * np.eye(3), X_REF))


@pytest.mark.parametrize("offset", [(0.002, -0.001, 0.003), (0.2, -0.15, 0.25)])
def test_the_bounded_pull_is_the_gradient_of_the_bounded_potential(offset):
    ev = _evaluator()
    ev.set_force_bound(20.0)
    x = X_REF + np.array(offset)
    h = 1e-6
    grad = np.array([(ev.potential(x + h * e) - ev.potential(x - h * e)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(ev.force(x, np.zeros(3)), -grad, rtol=1e-5, atol=1e-7)


def test_the_pull_never_exceeds_the_bound_and_is_unchanged_near_x_ref():
    plain, bounded = _evaluator(identity=True), _evaluator(identity=True)
    bounded.set_force_bound(30.0)
    rng = np.random.default_rng(0)
    for x in X_REF + rng.uniform(-0.4, 0.4, (200, 3)):
        assert np.linalg.norm(bounded.force(x, np.zeros(3))) <= 30.0 + 1e-9
        assert bounded.potential(x) <= plain.potential(x) + 1e-12
    near = X_REF + np.array([0.005, 0.004, -0.01])  # |S e| ~ 9 N: inside the bound
    np.testing.assert_array_equal(bounded.force(near, np.zeros(3)), plain.force(near, np.zeros(3)))
    far = X_REF + np.array([0.3, 0.0, 0.0])
    assert np.linalg.norm(plain.force(far, np.zeros(3))) > 400.0
    # along x, almost S's stiffest direction: the pull is almost the bound
    assert np.linalg.norm(bounded.force(far, np.zeros(3))) == pytest.approx(30.0, rel=0.01)
    bounded.set_force_bound(0.0)  # off again: the plain law, bit for bit
    np.testing.assert_array_equal(bounded.force(far, np.zeros(3)), plain.force(far, np.zeros(3)))


def test_the_controller_applies_its_laws_bound_to_every_evaluator_it_gets():
    arm = ArmModel()
    ctrl = FlowController(arm, _evaluator(), TorqueLawConfig(potential_force_bound=25.0))
    assert ctrl.evaluator.force_bound == 25.0
    other = _evaluator(identity=True)
    ctrl.set_evaluator(other)
    assert other.force_bound == 25.0
    ctrl.set_law(TorqueLawConfig())
    assert other.force_bound == 0.0
    with pytest.raises(ValueError, match="potential_force_bound"):
        TorqueLawConfig(potential_force_bound=-1.0)
    with pytest.raises(ValueError, match="force bound"):
        other.set_force_bound(float("nan"))


def test_in_process_rollouts_run_the_bounded_law_and_action_noise_refuses_it():
    from learner_node.config import TrainConfig
    from learner_node.rollout import RolloutRunner
    from learner_node.trainer import build_policy, make_evaluator

    with pytest.raises(ValueError, match="potential_force_bound needs exploration=params"):
        TrainConfig(task="gear", exploration="action", potential_force_bound=40.0)
    ends = []
    for bound in (0.0, 5.0):
        cfg = TrainConfig(task="gear", exploration="params", gains="learned", episode_seconds=0.2,
                          flow_init="identity", stiffness=300.0, damping=40.0, potential_force_bound=bound)
        runner = RolloutRunner(cfg)
        evaluator = make_evaluator(build_policy(cfg, runner.x_ref))
        rec = runner.run_episode(evaluator, None, 11, None)
        assert runner.controller.law.potential_force_bound == bound and evaluator.force_bound == bound
        ends.append(rec)
    # the same start, ~30 cm from x_ref: a 5 N pull moves the gear less far in 0.2 s than 300 N/m
    assert np.all(np.isfinite(ends[1].reward))
    assert float(np.sum(ends[1].reward)) < float(np.sum(ends[0].reward))
