"""The controller's episode core (ControlLoop + EpisodeRun, what the node runs over ROS) against the
in-process rollout of the trainer: same seeds -> the same decisions, actions and rewards."""

from __future__ import annotations

import numpy as np
import pytest

from learner_node.config import TrainConfig
from learner_node.trainer import Trainer, make_evaluator, policy_sigma
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import ControlLoop
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.episode import EpisodeRun, EpisodeSpec
from nf_core.reward import RewardWeights
from sim_bridge_node.env import InsertionEnv

NAMES = list(panda_spec.JOINT_NAMES)


CLOCK = [10_000_000]  # ns, the simulated clock shared by the tests of one loop (never runs backwards)


def run_loop_episode(loop: ControlLoop, env: InsertionEnv, spec: EpisodeSpec, start_seed: int,
                     resend_every: int = 0) -> EpisodeRun:
    """Drive ``loop`` like the lockstep node does: one state per step, stamps 1 ms apart. With
    ``resend_every`` = k, every k-th state is sent twice (a lockstep resend) and the second answer
    is the one applied."""
    env.reset(seed=start_seed)
    run = EpisodeRun(spec)
    stamp = CLOCK[0] = CLOCK[0] + 1_000_000_000
    loop.start_episode(run, stamp, world_was_reset=True)  # the lockstep sim teleported the arm
    step = 0
    while not run.done:
        loop.depth = env.insertion_depth
        tau, fault = loop.on_joint_state(NAMES, env.q, env.dq, stamp, 0.0)
        if resend_every and step % resend_every == 0:
            tau, fault = loop.on_joint_state(NAMES, env.q, env.dq, stamp, 0.0)
        step += 1
        assert not fault
        env.step(tau.copy())
        stamp += 1_000_000
    assert loop.end_episode() is run
    return run


@pytest.fixture(scope="module")
def gear_setup():
    cfg = TrainConfig.from_sources("config/gear.yaml", {"episode_seconds": 0.3, "rollouts_per_iter": 2})
    trainer = Trainer(cfg)
    params = trainer.policy.to_params(version=1)
    loop = ControlLoop(ArmModel(part=panda_spec.GEAR_PART))
    loop.set_policy(params)
    return cfg, trainer, loop, InsertionEnv("gear")


@pytest.mark.parametrize("deterministic", [False, True])
def test_loop_episode_matches_in_process_rollout(gear_setup, deterministic):
    cfg, trainer, loop, env = gear_setup
    sigma = None if deterministic else policy_sigma(trainer.policy)
    start, noise = 1234, 99
    ref = trainer.runner.run_episode(make_evaluator(trainer.policy), sigma, start,
                                     None if deterministic else np.random.default_rng(noise))
    spec = EpisodeSpec(episode_id=1, policy_version=1, duration=cfg.episode_seconds,
                       decision_period=cfg.decision_period, control_period=0.001, sigma=sigma,
                       noise_seed=noise, x_goal=trainer.x_ref, weights=RewardWeights(),
                       chunk_decisions=7)
    run = run_loop_episode(loop, env, spec, start)
    assert run.K == len(ref.reward) == 30
    np.testing.assert_allclose(run.x, ref.x, atol=1e-12)
    np.testing.assert_allclose(run.xdot, ref.xdot, atol=1e-12)
    np.testing.assert_allclose(run.u_mean, ref.u_mean, atol=1e-9)
    np.testing.assert_allclose(run.u_mean + run.eps, ref.action, atol=1e-9)
    np.testing.assert_allclose(run.reward, ref.reward, rtol=1e-9, atol=1e-9)
    assert run.mean_torque == pytest.approx(ref.torque_norm, rel=1e-9)
    chunks = run.ready_chunks()
    assert [c.seq for c in chunks] == [0, 1, 2, 3, 4]
    assert [c.final for c in chunks] == [False] * 4 + [True] and chunks[-1].n_chunks == 5
    np.testing.assert_allclose(np.concatenate([c.log_prob for c in chunks]), ref.log_prob, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([c.t for c in chunks]), ref.t)
    assert run.ready_chunks() == []  # handed out once


def test_resent_state_is_answered_but_not_recorded_twice(gear_setup):
    _cfg, trainer, loop, env = gear_setup
    env.reset(seed=5)
    spec = EpisodeSpec(episode_id=2, policy_version=1, duration=0.02, decision_period=0.01, control_period=0.001,
                       sigma=np.full(3, 2.0), noise_seed=3, x_goal=trainer.x_ref)
    run = EpisodeRun(spec)
    stamp = CLOCK[0] = CLOCK[0] + 1_000_000_000
    loop.start_episode(run, stamp, world_was_reset=True)
    tau1, _ = loop.on_joint_state(NAMES, env.q, env.dq, stamp, 0.0)
    tau1 = tau1.copy()
    eps = run.eps[0].copy()
    tau2, _ = loop.on_joint_state(NAMES, env.q, env.dq, stamp, 0.0)  # the lockstep resend of the same state
    assert run.steps == 1 and np.array_equal(run.eps[0], eps)
    np.testing.assert_allclose(tau2, tau1, atol=1e-12)
    loop.end_episode()


def test_resends_do_not_change_the_episode(gear_setup):
    """Resent states at every decision start, where large noise makes the torque rate limiter
    act, leave the episode exactly as without resends."""
    cfg, trainer, loop, env = gear_setup
    spec = EpisodeSpec(episode_id=3, policy_version=1, duration=0.1, decision_period=cfg.decision_period,
                       control_period=0.001, sigma=np.full(3, 40.0), noise_seed=8, x_goal=trainer.x_ref)
    plain = run_loop_episode(loop, env, spec, 77)
    q_plain = env.q.copy()
    resent = run_loop_episode(loop, env, spec, 77, resend_every=10)
    np.testing.assert_array_equal(env.q, q_plain)
    np.testing.assert_array_equal(resent.x, plain.x)
    np.testing.assert_array_equal(resent.reward, plain.reward)


def test_episode_refused_without_policy_and_bad_specs():
    loop = ControlLoop(ArmModel(part=panda_spec.GEAR_PART))
    spec = EpisodeSpec(episode_id=1, policy_version=0, duration=1.0, decision_period=0.01, control_period=0.001,
                       sigma=None, noise_seed=0, x_goal=np.zeros(3))
    with pytest.raises(ValueError, match="policy"):
        loop.start_episode(EpisodeRun(spec))
    for bad in ({"duration": float("nan")}, {"decision_period": 0.0001}, {"sigma": np.array([1.0, -1.0, 1.0])},
                {"chunk_decisions": 0}):
        kwargs = {**spec.__dict__, **bad}
        with pytest.raises(ValueError):
            EpisodeRun(EpisodeSpec(**kwargs))


def small_spec(sigma: np.ndarray | None = None, seed: int = 5) -> EpisodeSpec:
    """3 decisions of 2 states, 2-D."""
    return EpisodeSpec(episode_id=1, policy_version=1, duration=0.006, decision_period=0.002, control_period=0.001,
                       sigma=sigma, noise_seed=seed, x_goal=np.zeros(2), chunk_decisions=2)


def test_close_period_closes_a_decision_once_with_the_plants_state():
    run = EpisodeRun(small_spec())
    u = np.ones(2)
    with pytest.raises(RuntimeError, match="no open decision period"):
        run.close_period(np.zeros(2), np.zeros(2), 0.0)  # nothing recorded yet
    run.record(np.full(2, 0.1), np.zeros(2), u, np.nan, 1.0)
    with pytest.raises(RuntimeError, match="no open decision period"):
        run.close_period(np.zeros(2), np.zeros(2), 0.0)  # mid-period
    run.record(np.full(2, 0.2), np.zeros(2), None, np.nan, 1.0)
    run.close_period(np.full(2, 0.3), np.zeros(2), 0.004)  # the plant's state, not the controller's
    assert run.closed == 1 and run.depth[0] == 0.004
    with pytest.raises(RuntimeError, match="no open decision period"):
        run.close_period(np.zeros(2), np.zeros(2), 0.0)  # already closed
    run.record(np.full(2, 0.9), np.zeros(2), u, 0.5, 1.0)  # the next decision's first state: no second close
    assert run.closed == 1 and run.depth[0] == 0.004
    w = RewardWeights()
    d2 = 2 * 0.3**2  # from the closing state x = (0.3, 0.3), goal 0, at rest; action (1, 1)
    assert run.reward[0] == pytest.approx(-w.w * d2 - w.v * np.log1p(d2 / w.a) - w.action * 2.0, rel=1e-12)
    np.testing.assert_array_equal(run.x[1], [0.9, 0.9])
    for _ in range(3):  # the rest of decision 1 and all of decision 2
        run.record(np.zeros(2), np.zeros(2), u, np.nan, 1.0)
    run.record(np.zeros(2), np.zeros(2), None, 0.02, 0.0)  # the state after the last period closes it
    assert run.done and run.closed == 3 and run.depth[2] == 0.02
    assert run.final_distance == 0.0 and run.mean_torque == 1.0
    with pytest.raises(RuntimeError, match="no open decision period"):
        run.close_period(np.zeros(2), np.zeros(2), 0.0)


def test_a_given_generator_draws_the_noise_the_seed_would():
    sigma = np.array([2.0, 0.5])
    by_seed, by_rng = EpisodeRun(small_spec(sigma, seed=11)), EpisodeRun(small_spec(sigma, seed=0),
                                                                          rng=np.random.default_rng(11))
    for run in (by_seed, by_rng):
        for _ in range(7):
            run.noise()
            run.record(np.zeros(2), np.zeros(2), np.zeros(2), 0.0, 0.0)
    np.testing.assert_array_equal(by_seed.eps, by_rng.eps)
    np.testing.assert_array_equal(by_seed.log_prob(), by_rng.log_prob())
    assert np.all(by_seed.eps != 0.0)


def test_effort_of_a_driver_that_compensates_gravity_leaves_gravity_alone(gear_setup):
    """A Franka adds g(q) to our command: the episode's torque norm is then |tau| of the command, not
    |tau - g| (which reported the arm's ~40 Nm of gravity as effort on the robot path)."""
    cfg, trainer, _, env = gear_setup
    loop = ControlLoop(ArmModel(part=panda_spec.GEAR_PART), TorqueLawConfig(gravity_compensation=False))
    loop.set_policy(trainer.policy.to_params(version=1))
    spec = EpisodeSpec(episode_id=2, policy_version=1, duration=cfg.episode_seconds,
                       decision_period=cfg.decision_period, control_period=0.001, sigma=None, noise_seed=0,
                       x_goal=trainer.x_ref, weights=RewardWeights(), chunk_decisions=7)
    env.reset(seed=1234)
    run = EpisodeRun(spec)
    stamp = CLOCK[0] = CLOCK[0] + 1_000_000_000
    loop.start_episode(run, stamp, world_was_reset=True)
    norms, gravity = [], []
    while not run.done:
        loop.depth = env.insertion_depth
        tau, fault = loop.on_joint_state(NAMES, env.q, env.dq, stamp, 0.0)
        assert not fault
        g = loop.controller.arm.g.copy()
        norms.append(float(np.linalg.norm(tau)))
        gravity.append(float(np.linalg.norm(g)))
        env.step(tau + g)  # the driver adds gravity, as libfranka's robot does
        stamp += 1_000_000
    loop.end_episode()
    n = run.K * run.P  # the state that closes the last decision gets a command, not counted
    assert run.mean_torque == pytest.approx(np.mean(norms[:n]), rel=1e-9)
    assert run.mean_torque < 0.5 * np.mean(gravity), (run.mean_torque, np.mean(gravity))
