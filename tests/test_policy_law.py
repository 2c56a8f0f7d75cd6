"""A policy carries its law: the force bound, the orientation and null-space gains, the stiffness floor
and the held part travel with the flow, S, D and x_ref (message and checkpoint), and every controller
that runs the policy runs that law."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg

from learner_node.config import TrainConfig
from learner_node.deploy import load_checkpoint_policy, prepare
from learner_node.trainer import Trainer
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import ControlLoop
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyLaw, PolicyParameterError, PolicyParameters

CONFIG = "config/gear_learn.yaml"
Q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
DQ = np.array([0.1, -0.2, 0.05, 0.1, 0.3, -0.1, 0.2])


def _params(law: PolicyLaw, version: int = 1) -> PolicyParameters:
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=8, activation="gelu")
    weights = np.random.default_rng(3).uniform(-0.2, 0.2, arch.n_params)
    return PolicyParameters(arch, weights, np.zeros(1), np.diag([900.0, 800.0, 700.0]), 40.0 * np.eye(3),
                            np.array([0.45, 0.05, 0.3]), version=version, law=law)


@pytest.fixture(scope="module")
def arm():
    return ArmModel(part=panda_spec.GEAR_PART)


def test_the_law_round_trips_through_the_message():
    law = PolicyLaw(potential_force_bound=60.0, k_rot=40.0, d_rot=4.0, joint_damping=0.7, stiffness_floor=250.0,
                    held_part="gear")
    back = PolicyParameters.from_msg(_params(law).fill_msg(PolicyParametersMsg()))
    assert back.law == law


@pytest.mark.parametrize(("field", "value", "match"), [
    ("held_part", "", "held_part must be one of"),
    ("k_rot", -1.0, "k_rot must be finite and >= 0"),
    ("potential_force_bound", float("nan"), "potential_force_bound must be finite"),
])
def test_a_message_with_a_bad_law_is_refused(field, value, match):
    msg = _params(PolicyLaw()).fill_msg(PolicyParametersMsg())
    setattr(msg, field, value)
    with pytest.raises(PolicyParameterError, match=match):
        PolicyParameters.from_msg(msg)


def test_gains_beyond_the_limits_and_s_below_the_floor_are_refused():
    with pytest.raises(PolicyParameterError, match="k_rot 1e\\+03 Nm/rad, at most 300"):
        _params(PolicyLaw(k_rot=1000.0)).check_limits()
    with pytest.raises(PolicyParameterError, match="below the law's stiffness_floor 750"):
        _params(PolicyLaw(stiffness_floor=750.0))


def test_the_controller_runs_the_law_the_policy_carries(arm):
    """The torque of a loop that installed a policy equals a controller built directly with that law,
    and differs from the same policy under the default law (the bound and gains act)."""
    law = PolicyLaw(potential_force_bound=20.0, k_rot=50.0, d_rot=5.0, joint_damping=1.0)
    params = _params(law)
    loop = ControlLoop(arm)
    assert loop.set_policy(params)
    assert (loop.controller.law.k_rot, loop.controller.law.potential_force_bound) == (50.0, 20.0)
    direct = FlowController(arm, FlowEvaluator.from_params(params),
                            TorqueLawConfig(potential_force_bound=20.0, k_rot=50.0, d_rot=5.0, joint_damping=1.0))
    default = FlowController(arm, FlowEvaluator.from_params(params), TorqueLawConfig())
    tau = loop.controller.step(Q, DQ).copy()
    np.testing.assert_allclose(tau, direct.step(Q, DQ), rtol=0, atol=1e-12)
    assert np.max(np.abs(tau - default.step(Q, DQ))) > 0.1
    # the next policy with the default law puts the default gains back
    assert loop.set_policy(dataclasses.replace(params, law=PolicyLaw(), version=2))
    assert (loop.controller.law.k_rot, loop.controller.law.potential_force_bound) == (30.0, 0.0)


def test_a_policy_learned_with_another_part_in_the_hand_is_refused(arm):
    loop = ControlLoop(arm)
    with pytest.raises(PolicyParameterError, match="learned with held_part 'peg'; this controller's hand holds 'gear'"):
        loop.set_policy(_params(PolicyLaw(held_part="peg")))
    assert loop.policy is None


def test_the_checkpoint_carries_the_law_and_deploy_policy_sends_it(tmp_path):
    cfg = TrainConfig.from_sources(CONFIG, {"iterations": 1, "eval_episodes": 1})
    trainer = Trainer(cfg)
    assert trainer.policy.to_params().law == cfg.policy_law() == PolicyLaw(potential_force_bound=60.0)
    trainer.save_checkpoint(tmp_path / "checkpoint.pt")
    params, _, scale = load_checkpoint_policy(tmp_path / "checkpoint.pt")
    assert params.law == PolicyLaw(potential_force_bound=60.0)
    lifted = prepare(params, None, 5, scale, stiffness_floor=400.0)
    assert lifted.law.stiffness_floor == 400.0 and np.all(np.diag(lifted.stiffness) >= 400.0)
    assert PolicyParameters.from_msg(lifted.fill_msg(PolicyParametersMsg())).law == lifted.law


def test_the_learners_own_rollouts_run_the_same_law(tmp_path):
    """The in-process rollouts (training, evaluation, make run's GIF) build their controller from the law
    the policy carries to the arm."""
    trainer = Trainer(TrainConfig.from_sources(CONFIG, {"iterations": 1, "eval_episodes": 1,
                                                        "episode_seconds": 0.05}))
    trainer.evaluate(1)
    law = trainer.runner.controller.law
    carried = trainer.policy.to_params().law
    assert (law.potential_force_bound, law.k_rot, law.d_rot, law.joint_damping) == (
        carried.potential_force_bound, carried.k_rot, carried.d_rot, carried.joint_damping)
