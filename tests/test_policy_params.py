"""Policy-parameter validation: malformed messages are rejected with a clear error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameterError, PolicyParameters

from interface_samples import policy_parameters


def test_valid_message_round_trips():
    msg = policy_parameters()
    params = PolicyParameters.from_msg(msg)
    assert params.arch == FlowArchitecture(3, 2, 16, "gelu")
    assert params.weights.size == params.arch.n_params
    out = params.fill_msg(type(msg)())
    assert list(out.weights) == list(msg.weights) and list(out.stiffness) == list(msg.stiffness)


def test_param_count_matches_layout():
    arch = FlowArchitecture(dim=3, n_flow=2, n_hidden=16)
    # layer with 1 conditioning, 2 transformed dims and the swapped one, s and t MLPs each
    def mlp(i, o):
        return 16 * i + 16 + 16 * 16 + 16 + o * 16 + o
    assert arch.n_params == 2 * 2 * (mlp(1, 2) + mlp(2, 1))


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("weights", [0.1] * 10, r"weights: expected \d+ values, got 10"),
        ("weights", "nan", r"weights: 1 non-finite value\(s\), first at index 5"),
        ("log_std", [0.0, 0.0], r"log_std: expected 1 or 3 values, got 2"),
        ("stiffness", [1.0] * 4, r"stiffness S: expected 9 values, got 4"),
        ("stiffness", [1.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], r"stiffness S: matrix is not symmetric"),
        ("damping", (-np.eye(3)).reshape(-1).tolist(), r"damping D: matrix is not positive definite"),
        ("x_ref", [0.0, math.inf, 0.0], r"x_ref: 1 non-finite"),
        ("x_ref", [0.0, 0.0], r"x_ref: expected 3 values, got 2"),
        ("activation", "relu", r"architecture: activation must be one of"),
        ("dim", 4, r"architecture: flow dim must be 2 or 3"),
        ("n_flow", 0, r"architecture: n_flow must be in"),
    ],
)
def test_malformed_message_is_rejected(field, value, match):
    msg = policy_parameters()
    if value == "nan":
        weights = list(msg.weights)
        weights[5] = math.nan
        msg.weights = weights
    else:
        setattr(msg, field, value)
    with pytest.raises(PolicyParameterError, match=match):
        PolicyParameters.from_msg(msg)
