"""Environment API: starts, determinism, bad input, task-space state, batching."""

from __future__ import annotations

import numpy as np
import pytest
from sim_testing import full_state, push_rollout

from nf_core import panda_spec
from nf_core.task_spec import load_task
from sim_bridge_node.batched_env import BatchedEnv
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scenes import TASKS, build_scene
from sim_bridge_node.scripted_insertion import HAND_DOWN, push_torque


@pytest.fixture(scope="module")
def gear_env():
    return InsertionEnv("gear")


@pytest.fixture(scope="module")
def block_env():
    return InsertionEnv("block")




@pytest.mark.parametrize("task", ["gear", "peg"])
def test_fixed_start_points_down_above_the_fixture(task):
    env = InsertionEnv(task)
    obs = env.reset()
    np.testing.assert_array_equal(obs.q, env.q_mean)
    spec = load_task(task)
    np.testing.assert_allclose(obs.x, spec.top + [0.0, 0.0, spec.start.height], atol=1e-5)
    np.testing.assert_allclose(env.tcp_rotation, HAND_DOWN, atol=1e-5)
    np.testing.assert_array_equal(obs.dq, 0.0)
    assert env.time == 0.0 and env.insertion_depth == 0.0 and not env.success
    np.testing.assert_allclose(env.goal_position, spec.top - [0.0, 0.0, 0.02])


def test_every_name_is_set():
    for task in TASKS:
        model = build_scene(task).model
        for kind, count in (("body", model.nbody), ("joint", model.njnt), ("geom", model.ngeom),
                            ("site", model.nsite), ("actuator", model.nu)):
            names = [getattr(model, kind)(i).name for i in range(count)]
            assert all(names[1 if kind == "body" else 0:]), (task, kind, names)
            assert len(set(names)) == len(names), (task, kind)


def test_same_seed_gives_bit_identical_trajectory(gear_env):
    first = push_rollout(gear_env, seed=11, steps=300)
    second = push_rollout(gear_env, seed=11, steps=300)
    np.testing.assert_array_equal(first, second)
    fixed = push_rollout(gear_env, seed=None, steps=50)
    np.testing.assert_array_equal(fixed, push_rollout(gear_env, seed=-3, steps=50))


@pytest.mark.parametrize("task", TASKS)
def test_state_views_follow_every_step_and_reset(task):
    """``state_views`` (what the composed tick reads instead of two copies) are MuJoCo's own q and
    dq: equal to the copies, rewritten in place by each step and reset, never stale."""
    env = InsertionEnv(task)
    views = env.state_views()
    if views is None:
        pytest.skip(f"{task}: joints not contiguous in MuJoCo's arrays (callers use the copies)")
    q, dq = views
    env.reset(seed=3)
    for _ in range(5):
        np.testing.assert_array_equal(q, env.q)
        np.testing.assert_array_equal(dq, env.dq)
        env.step(np.zeros(env.nu))
    start = env.reset(seed=4).q
    np.testing.assert_array_equal(q, start)  # still the live state after a reset
    assert np.shares_memory(q, env.data.qpos) and np.shares_memory(dq, env.data.qvel)


def test_different_seeds_give_different_starts(gear_env, block_env):
    for env in (gear_env, block_env):
        starts = np.array([env.reset(seed=s).q for s in range(10)])
        assert len({tuple(q) for q in starts}) == 10
        assert not np.allclose(starts[0], env.q_mean)


@pytest.mark.parametrize("task", ["gear", "peg", "block"])
def test_sampled_starts_are_valid(task):
    env = InsertionEnv(task)
    lo, hi = env.q_limits
    spread = []
    for seed in range(50):
        obs = env.reset(seed=seed)
        assert np.all(obs.q > lo) and np.all(obs.q < hi), seed
        assert env.data.ncon == 0, (seed, env.data.ncon)
        assert obs.x[2] > env.scene.insertion_top, seed
        spread.append(obs.q - env.q_mean)
    std = np.std(spread, axis=0)
    expected = env.start_std
    assert np.all(std > 0.5 * expected) and np.all(std < 1.5 * expected), std


def test_block_start_distribution():
    env = InsertionEnv("block")
    np.testing.assert_allclose(env.start_std, [0.05, 0.10])
    np.testing.assert_allclose(env.reset().x, env.goal_position + [0.10, 0.0, 0.25])


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.array([0.0, 0.0, np.nan, 0.0, 0.0, 0.0, 0.0]), "NaN or Inf"),
        (np.array([0.0, np.inf, 0.0, 0.0, 0.0, 0.0, 0.0]), "NaN or Inf"),
        (np.zeros(6), r"shape \(7,\)"),
        (np.zeros((7, 1)), r"shape \(7,\)"),
        ("torques", "numeric"),
    ],
)
def test_bad_torque_is_rejected_and_state_unchanged(gear_env, bad, message):
    gear_env.reset(seed=5)
    for _ in range(10):
        gear_env.step(gear_env.bias_torques)
    before = full_state(gear_env)
    with pytest.raises(ValueError, match=message):
        gear_env.step(bad)
    np.testing.assert_array_equal(full_state(gear_env), before)


def test_torques_are_clamped(gear_env):
    gear_env.reset()
    gear_env.step(np.full(7, 1e6))
    np.testing.assert_array_equal(gear_env.last_torque, panda_spec.TORQUE_LIMITS)
    np.testing.assert_array_equal(gear_env.data.ctrl, panda_spec.TORQUE_LIMITS)


def test_bad_explicit_start_is_rejected(gear_env):
    with pytest.raises(ValueError, match="joint limits"):
        gear_env.reset(q=panda_spec.Q_MAX + 0.1)
    with pytest.raises(ValueError, match="shape"):
        gear_env.reset(q=np.zeros(3))
    q = gear_env.q_mean + 0.05
    np.testing.assert_array_equal(gear_env.reset(q=q).q, q)


def test_task_space_state_matches_kinematics(gear_env):
    gear_env.reset(seed=2)
    for _ in range(200):
        gear_env.step(push_torque(gear_env, gear_env.goal_position + [0.05, 0.05, 0.1]))
    jac = gear_env.tcp_jacobian()
    np.testing.assert_allclose(gear_env.xdot, jac[:3] @ gear_env.dq, atol=1e-12)
    assert np.linalg.norm(gear_env.xdot) > 1e-3
    # x and xdot belong to the current q: a finite difference over one more step agrees
    x0, v0 = gear_env.x, gear_env.xdot
    gear_env.step(gear_env.last_torque)
    np.testing.assert_allclose((gear_env.x - x0) / 0.001, 0.5 * (v0 + gear_env.xdot), atol=2e-3)
    assert gear_env.time == pytest.approx(0.201)


def test_gravity_compensation_holds_still(gear_env):
    gear_env.reset()
    for _ in range(500):
        gear_env.step(gear_env.bias_torques)
    assert np.abs(gear_env.dq).max() < 1e-6
    np.testing.assert_allclose(gear_env.q, gear_env.q_mean, atol=1e-6)


def test_batched_env_matches_single_envs():
    seeds = [3, None, 8]
    steps = 120
    with BatchedEnv("gear", n_envs=3, n_threads=2) as batch:
        batch.reset(seeds)
        for _ in range(steps):
            batch.step(np.stack([push_torque(e, e.goal_position + [0, 0, 0.03]) for e in batch.envs]))
        batched_q = batch.q
        assert batch.x.shape == (3, 3) and batch.success.shape == (3,)
        np.testing.assert_allclose(batch.time, steps * 0.001, rtol=1e-12)
        before = batch.q
        with pytest.raises(ValueError, match="environments \\[1\\]"):
            bad = np.zeros((3, 7))
            bad[1, 2] = np.nan
            batch.step(bad)
        with pytest.raises(ValueError, match="shape"):
            batch.step(np.zeros((2, 7)))
        np.testing.assert_array_equal(batch.q, before)
    single = InsertionEnv("gear")
    for i, seed in enumerate(seeds):
        single.reset(seed)
        for _ in range(steps):
            single.step(push_torque(single, single.goal_position + [0, 0, 0.03]))
        np.testing.assert_array_equal(single.q, batched_q[i])
