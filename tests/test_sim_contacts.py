"""Contact honesty: the same scripted push seats an aligned part and jams a misaligned one.

The push is a Jacobian-transpose Cartesian impedance with gravity compensation (qfrc_bias) to a
target 5 mm below the fully inserted position, descending slowly from just above the mouth.
"""

from __future__ import annotations

import numpy as np
import pytest

from nf_core import panda_spec
from nf_core.task_spec import load_task
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scripted_insertion import run_insertion

MAX_PENETRATION = 0.0005  # m


@pytest.fixture(scope="module", params=["gear", "peg"])
def arm_env(request):
    return InsertionEnv(request.param)


def test_aligned_part_slides_home(arm_env):
    arm_env.reset()
    result = run_insertion(arm_env, seconds=3.0)
    assert result["success"], result
    assert result["depth"] >= 0.019  # seated: 20 mm full depth
    assert result["max_penetration"] < MAX_PENETRATION
    assert result["penetration"] < MAX_PENETRATION
    # resting on the shoulder / hole bottom: the contact pushes the part up
    assert result["contact_force"][2] > 1.0
    np.testing.assert_allclose(result["x"], arm_env.goal_position, atol=0.0015)


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, -1.0)])
def test_part_offset_by_3mm_jams_on_top(arm_env, direction):
    arm_env.reset()
    offset = 0.003 * np.array([*direction, 0.0])
    result = run_insertion(arm_env, offset=offset, seconds=2.6)
    assert not result["success"], result
    assert result["depth"] < 0.001  # stopped on the shaft top / hole rim
    assert result["x"][2] > arm_env.scene.insertion_top - 0.001
    assert result["max_penetration"] < MAX_PENETRATION
    assert result["contact_force"][2] > 10.0  # the push is carried by the contact


def test_gear_bore_clearance_is_one_millimetre():
    """The bore is a 16-gon of inradius 15 mm around a 28 mm shaft: 1.0-1.3 mm radial play."""
    env = InsertionEnv("gear")
    model = env.model
    shaft = model.geom("shaft_pin")
    assert shaft.size[0] == pytest.approx(0.014)
    assert 2 * shaft.size[1] == pytest.approx(load_task("gear").fixture.shaft_length)
    inner = []
    for k in range(16):
        g = model.geom(f"gear_segment_{k}")
        inner.append(np.hypot(*g.pos[:2]) - g.size[0])
        assert 2 * g.size[2] == pytest.approx(panda_spec.GEAR_DEPTH)
    np.testing.assert_allclose(inner, panda_spec.GEAR_BORE_RADIUS, atol=1e-12)
    assert model.body("gear").mass[0] == pytest.approx(panda_spec.GEAR_MASS)


@pytest.mark.parametrize("plane", ["vertical", "horizontal"])
def test_block_slides_into_slot_when_aligned(plane):
    env = InsertionEnv("block", plane=plane)
    env.reset()
    result = run_insertion(env, seconds=3.0, speed=0.05)
    assert result["success"], result
    assert result["depth"] >= 0.049
    assert result["max_penetration"] < MAX_PENETRATION


def test_block_offset_jams_on_wall():
    env = InsertionEnv("block")
    env.reset()
    result = run_insertion(env, offset=(0.004, 0.0, 0.0), seconds=2.0, speed=0.05)
    assert not result["success"]
    assert result["depth"] < 0.001
    assert result["contact_force"][2] > 1.0
