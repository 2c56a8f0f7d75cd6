"""Policies that are well-formed but absurd (issue 16, item 6) are refused by the controller with a
clear reason, and the policy in use stays; the settings the project trains with pass."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import ControlLoop
from nf_core import policy_params
from nf_core.flow_spec import FlowArchitecture
from nf_core.panda_spec import GEAR_PART, PEG_PART
from nf_core.policy_params import PolicyParameterError, PolicyParameters

ARCH = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
X_REF = np.array([0.5, 0.0, 0.11])


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(part=GEAR_PART)


def _params(version: int = 1, arch: FlowArchitecture = ARCH, **kw) -> PolicyParameters:
    fields = dict(weights=np.random.default_rng(0).uniform(-0.25, 0.25, arch.n_params), log_std=np.zeros(1),
                  stiffness=300.0 * np.eye(3), damping=40.0 * np.eye(3), x_ref=X_REF.copy())
    fields.update(kw)
    return PolicyParameters(arch, version=version, **fields)


def _huge_weight() -> np.ndarray:
    w = np.random.default_rng(0).uniform(-0.25, 0.25, ARCH.n_params)
    w[17] = 1e6
    return w


ABSURD = {
    "log_std 700": (dict(log_std=np.array([700.0])), "log_std"),
    "log_std -700": (dict(log_std=np.array([-700.0])), "log_std"),
    "noise std 100 N on one axis": (dict(log_std=np.log([1.0, 100.0, 1.0])), "log_std"),
    "S 1e300": (dict(stiffness=1e300 * np.eye(3)), "stiffness S: largest eigenvalue"),
    "S 2e4": (dict(stiffness=np.diag([300.0, 2e4, 300.0])), "stiffness S: largest eigenvalue"),
    "D 1e300": (dict(damping=1e300 * np.eye(3)), "damping D: largest eigenvalue"),
    "D 5e3": (dict(damping=5e3 * np.eye(3)), "damping D: largest eigenvalue"),
    "x_ref 1e300 m": (dict(x_ref=np.array([1e300, 0.0, 0.0])), "x_ref"),
    "x_ref 1 km": (dict(x_ref=np.array([0.0, 1000.0, 0.0])), "x_ref"),
    "x_ref 1.3 m": (dict(x_ref=np.array([0.9, 0.9, 0.3])), "beyond its reach"),
    "weight 1e6": (dict(weights=_huge_weight()), "weights"),
}


@pytest.mark.parametrize("kind", ABSURD)
def test_absurd_policy_rejected_with_a_reason_and_the_old_one_stays(arm, kind):
    change, match = ABSURD[kind]
    loop = ControlLoop(arm)
    assert loop.set_policy(_params(version=1))
    with pytest.raises(PolicyParameterError, match=match) as info:
        loop.set_policy(_params(version=2, **change))
    assert len(str(info.value)) <= 300
    assert loop.policy_version == 1 and loop.policy.x_ref.tolist() == X_REF.tolist()


def test_version_must_not_go_backwards_but_may_repeat(arm):
    loop = ControlLoop(arm)
    assert loop.set_policy(_params(version=5))
    assert loop.set_policy(_params(version=5)), "the same version again (a latched re-send) is fine"
    with pytest.raises(PolicyParameterError, match="version 4 is older than version 5"):
        loop.set_policy(_params(version=4))
    loop.episode_active = True
    assert not loop.set_policy(_params(version=7))  # queued
    with pytest.raises(PolicyParameterError, match="version 6 is older than version 7"):
        loop.set_policy(_params(version=6))
    loop.end_episode()
    assert loop.policy_version == 7


def test_flow_too_large_for_the_1khz_step(arm):
    loop = ControlLoop(arm)
    big = FlowArchitecture(dim=3, n_flow=2, n_hidden=512, activation="gelu")  # 2.1 M weights
    with pytest.raises(PolicyParameterError, match="flow too large for the 1 kHz step"):
        loop.set_policy(_params(arch=big, weights=np.zeros(big.n_params)))
    limit = policy_params.POLICY_LIMITS.max_flow_params
    assert FlowArchitecture(3, 4, 32).n_params <= limit, "the sizes the project uses fit"


def test_limits_live_in_one_named_place():
    limits = policy_params.POLICY_LIMITS
    assert isinstance(limits, policy_params.PolicyLimits)
    assert limits.max_reach == 1.2 and limits.max_stiffness == 1e4 and limits.max_damping == 1e3
    strict = policy_params.PolicyLimits(max_stiffness=100.0)
    with pytest.raises(PolicyParameterError, match="stiffness"):
        _params().check_limits(strict)


@pytest.mark.parametrize("task", ["gear", "peg"])
def test_the_trained_settings_pass(arm, task):
    """The controller accepts what the learner sends for the arm tasks (initial policy, config gains)."""
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer

    cfg = TrainConfig.from_sources(f"config/{task}.yaml", {"episode_seconds": 0.1, "rollouts_per_iter": 1})
    params = Trainer(cfg).policy.to_params(version=0)
    params.check_limits()
    assert params.law.held_part == task  # the part the simulated hand held: the controller's must be it too
    loop = ControlLoop(arm if task == "gear" else ArmModel(part=PEG_PART))
    assert loop.set_policy(params)
    for sigma in (0.5, 5.0, 30.0):
        params.log_std = np.array([math.log(sigma)])
        params.version += 1
        assert loop.set_policy(params)


def test_prepared_policy_is_checked_off_thread_and_its_version_again_on_install(arm):
    """The node checks and builds on its executor thread (prepare_policy) and installs on the tick's
    thread (set_policy with the evaluator): a version that went backwards meanwhile is refused."""
    loop = ControlLoop(arm)
    with pytest.raises(PolicyParameterError, match="weights"):
        loop.prepare_policy(_params(version=3, weights=_huge_weight()))
    old = _params(version=4)
    evaluator = loop.prepare_policy(old)
    assert loop.set_policy(_params(version=6))
    with pytest.raises(PolicyParameterError, match="version 4 is older than version 6"):
        loop.set_policy(old, evaluator)
    newer = _params(version=7)
    assert loop.set_policy(newer, loop.prepare_policy(newer)) and loop.policy_version == 7


def test_gains_clamped_in_log_space_to_the_bound_pass(arm):
    """A learner clamping log-gains at log(bound) sends exp(log(1e4)) = 10000.00000000001."""
    limits = policy_params.POLICY_LIMITS
    for dtype in (np.float64, np.float32):
        s = float(np.exp(np.asarray(math.log(limits.max_stiffness), dtype=dtype)))
        d = float(np.exp(np.asarray(math.log(limits.max_damping), dtype=dtype)))
        _params(stiffness=np.diag([s, 300.0, 300.0]), damping=np.diag([d, 40.0, 40.0])).check_limits()
