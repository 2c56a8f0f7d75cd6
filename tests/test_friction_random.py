"""Joint friction randomized per episode (issue 30, ``nf_core.friction``): the draw is a pure function
of the start seed and leaves the starts alone, ranges [0, 0] change nothing, bad ranges are refused,
and the in-process trainer and the sim node apply the same friction for a seed (both through
``InsertionEnv.reset(seed)``). The sim node is built in process, with no ROS graph around it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from nf_msgs.srv import ResetSim
from sim_testing import push_rollout

from learner_node.config import TrainConfig
from learner_node.rollout import friction_info
from learner_node.trainer import EVAL_SEED_BASE, Trainer
from nf_core import panda_spec
from nf_core.friction import FrictionRanges
from sim_bridge_node.batched_env import BatchedEnv
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scripted_insertion import push_torque

CONFIG = Path(__file__).resolve().parents[1] / "config"
FRICTION_OVERLAY = CONFIG / "friction.yaml"
FRICTION_YAML = [CONFIG / "gear_learn.yaml", FRICTION_OVERLAY]  # the task file, then the overlay
RANGES = FrictionRanges((0.2, 1.2), (0.0, 0.2))
SEEDS = (0, 7, 123_456, EVAL_SEED_BASE + 3)
TINY = {"iterations": 1, "rollouts_per_iter": 2, "episode_seconds": 0.05, "eval_episodes": 1}


def test_the_draw_is_a_pure_function_of_the_seed_and_leaves_the_start_alone():
    plain, randomized, again = InsertionEnv("gear"), InsertionEnv("gear"), InsertionEnv("gear")
    randomized.set_friction_ranges(RANGES)
    again.set_friction_ranges(RANGES)
    base_damping = plain.joint_friction[1]
    draws = []
    for seed in SEEDS:
        q_plain = plain.reset(seed).q
        q_random = randomized.reset(seed).q
        np.testing.assert_array_equal(q_random, q_plain)  # the start has its own stream
        coulomb, viscous = RANGES.draw(seed, 7)
        assert np.all((coulomb >= 0.2) & (coulomb <= 1.2)) and np.all((viscous >= 0.0) & (viscous <= 0.2))
        np.testing.assert_array_equal(randomized.episode_friction[0], coulomb)
        np.testing.assert_array_equal(randomized.episode_friction[1], viscous)
        model_coulomb, model_damping = randomized.joint_friction
        np.testing.assert_array_equal(model_coulomb, coulomb)
        np.testing.assert_array_equal(model_damping, base_damping + viscous)
        draws.append(coulomb)
    for seed in reversed(SEEDS):  # another env, another order: the same draw per seed
        again.reset(seed)
        np.testing.assert_array_equal(again.joint_friction[0], RANGES.draw(seed, 7)[0])
    assert len({tuple(d) for d in draws}) == len(SEEDS)  # seeds differ, held-out ones included
    for seed in (None, -1):  # the fixed start: the ranges' middles
        randomized.reset(seed)
        np.testing.assert_array_equal(randomized.episode_friction[0], np.full(7, 0.7))
        np.testing.assert_array_equal(randomized.episode_friction[1], np.full(7, 0.1))
    # the physics follows the draw: with friction the same push ends elsewhere
    assert not np.array_equal(push_rollout(randomized, 7, 50), push_rollout(plain, 7, 50))
    np.testing.assert_array_equal(push_rollout(randomized, 7, 50), push_rollout(again, 7, 50))


def test_ranges_off_leave_the_model_and_the_trajectory_bit_identical():
    today = InsertionEnv("gear")  # never told about ranges: the code path as it was
    off = InsertionEnv("gear")
    off.set_friction_ranges(FrictionRanges())
    runner_env = Trainer(TrainConfig.from_sources(CONFIG / "gear_learn.yaml", TINY)).runner.env  # default [0, 0]
    for env in (off, runner_env):
        for seed in (11, None):
            np.testing.assert_array_equal(push_rollout(env, seed, 200), push_rollout(today, seed, 200))
            assert env.episode_friction is None
        for name in ("dof_frictionloss", "dof_damping"):
            np.testing.assert_array_equal(getattr(env.model, name), getattr(today.model, name))
    # fixed friction (joint_friction) stays as set when the ranges are off
    off.set_joint_friction(0.4, 0.0)
    off.reset(3)
    assert np.all(off.joint_friction[0] == 0.4)


@pytest.mark.parametrize("coulomb, viscous, words", [
    ([1.0, 0.5], [0.0, 0.0], "friction_coulomb must have lo <= hi"),
    ([0.0, 0.0], [-0.1, 0.2], "friction_viscous must be >= 0"),
    ([0.2], [0.0, 0.0], "friction_coulomb must be a range [lo, hi]"),
    ([0.2, 0.3, 0.4], [0.0, 0.0], "friction_coulomb must be a range [lo, hi]"),
    ([0.0, 0.0], [0.0, float("inf")], "friction_viscous must be finite"),
    ("0.2, 1.2", [0.0, 0.0], "friction_coulomb must be a range [lo, hi]"),
    ([True, 1.0], [0.0, 0.0], "friction_coulomb must be a range [lo, hi]"),
])
def test_bad_ranges_are_refused(coulomb, viscous, words):
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
        FrictionRanges(coulomb, viscous)
    if isinstance(coulomb, list) and not any(isinstance(v, bool) for v in coulomb):
        with pytest.raises(ValueError, match=words.split(" must")[0]):  # the trainer names it too
            TrainConfig(friction_coulomb=coulomb, friction_viscous=viscous)


def test_the_trainer_config_reads_the_ranges_and_refuses_a_fixed_start_with_random_friction():
    cfg = TrainConfig.from_sources(FRICTION_YAML)
    assert cfg.friction_ranges() == RANGES
    # the overlay adds the two ranges and turns the force bound off (the robot's controller has none)
    assert cfg == TrainConfig.from_sources(CONFIG / "gear_learn.yaml",
                                           {"friction_coulomb": "0.2, 1.2", "friction_viscous": "[0.0, 0.2]",
                                            "potential_force_bound": 0.0})
    assert not TrainConfig().friction_ranges().enabled  # off by default
    assert TrainConfig(friction_coulomb=[0, 1]).friction_coulomb == [0.0, 1.0]  # YAML [0, 1]: ints
    with pytest.raises(ValueError, match="start: fixed"):
        TrainConfig(start="fixed", friction_coulomb=[0.2, 1.2])
    assert TrainConfig(start="fixed", friction_coulomb=[0.5, 0.5]).friction_ranges().enabled  # one value: fine


def test_trainer_records_and_evaluations_show_the_drawn_friction():
    cfg = TrainConfig.from_sources(FRICTION_YAML, TINY)
    trainer = Trainer(cfg)
    starts = [start for start, _, _ in Trainer(cfg).episode_plan()]  # the same generator: the same plan
    row = trainer.train_iteration()
    expect = [friction_info(cfg.friction_ranges(), s, 7) for s in starts]
    assert row["friction_coulomb_mean"] == pytest.approx(np.mean([e["friction_coulomb"] for e in expect]), rel=1e-12)
    assert row["friction_viscous_mean"] == pytest.approx(np.mean([e["friction_viscous"] for e in expect]), rel=1e-12)
    per = trainer.evaluate()["per_episode"][0]
    held_out = RANGES.draw(EVAL_SEED_BASE, 7)
    assert per["friction_coulomb_mean"] == pytest.approx(float(np.mean(held_out[0])), rel=1e-12)
    assert per["friction_viscous_mean"] == pytest.approx(float(np.mean(held_out[1])), rel=1e-12)
    plain = Trainer(TrainConfig.from_sources(CONFIG / "gear_learn.yaml", TINY)).train_iteration()
    assert not any(k.startswith("friction") for k in plain)  # off: the columns are what they were


def test_batched_envs_with_friction_match_lone_envs():
    seeds = [3, None, 8]
    with BatchedEnv("gear", n_envs=3, n_threads=2, friction=RANGES) as batch:
        batch.reset(seeds)
        assert len({id(e.model) for e in batch.envs}) == 3  # each its own model
        for _ in range(60):
            batch.step(np.stack([push_torque(e, e.goal_position + [0, 0, 0.03]) for e in batch.envs]))
        batched = batch.q
    single = InsertionEnv("gear")
    single.set_friction_ranges(RANGES)
    for i, seed in enumerate(seeds):
        single.reset(seed)
        for _ in range(60):
            single.step(push_torque(single, single.goal_position + [0, 0, 0.03]))
        np.testing.assert_array_equal(batched[i], single.q)


def test_the_sim_node_applies_the_trainers_friction_for_a_seed(ros_args):
    """The task file's shared ranges reach the sim node; its ~/reset with a seed (what the controller
    sends for a RunEpisode goal) gives the same start and friction as the in-process runner's reset,
    and /diagnostics carries the draw."""
    from sim_bridge_node.node import SimBridgeNode

    ros_args("--params-file", str(FRICTION_YAML[0]), "--params-file", str(FRICTION_YAML[1]))
    node = SimBridgeNode()
    try:
        runner = Trainer(TrainConfig.from_sources(FRICTION_YAML, TINY)).runner
        sent = []
        node._diag_pub.publish = sent.append
        for seed in (5, EVAL_SEED_BASE + 1):
            response = node._on_reset(ResetSim.Request(seed=seed), ResetSim.Response())
            assert response.success, response.message
            runner.env.reset(seed=runner.start_seed(seed))
            np.testing.assert_array_equal(np.array(response.q), runner.env.q)
            for mine, theirs in zip(node.bridge.env.joint_friction, runner.env.joint_friction, strict=True):
                np.testing.assert_array_equal(mine, theirs)
            info = friction_info(runner.friction, seed, len(panda_spec.JOINT_NAMES))  # the learner over ROS
            np.testing.assert_array_equal(node.bridge.env.episode_friction[0], info["friction_coulomb"])
            node._publish_diagnostics()
            values = {kv.key: kv.value for kv in sent[-1].status[0].values}
            assert values["episode_friction_coulomb"] == str(np.round(info["friction_coulomb"], 4).tolist())
    finally:
        node.destroy_node()


@pytest.mark.parametrize("args, expect", [
    (["-p", "friction_coulomb:=[0.2, 1.2]", "-p", "joint_friction:=0.4"], "are both set"),
    (["-p", "friction_viscous:=[0.3, 0.1]"], "friction_viscous must have lo <= hi"),
    (["-p", "friction_coulomb:=0.5"], "friction_coulomb must be a range"),
])
def test_the_sim_node_refuses_bad_ranges_and_fixed_friction_with_ranges(ros_args, args, expect):
    from sim_bridge_node.node import SimBridgeNode

    ros_args(*args)
    with pytest.raises(ValueError, match=expect):
        SimBridgeNode()


def test_the_robot_run_refuses_a_task_file_with_simulated_friction(tmp_path, capsys):
    """run_robot's learner would record friction draws the arm never had: the friction file is for
    training in simulation, its policy reaches the arm through --from-checkpoint."""
    from nf_bringup.robot_run import _parse

    with pytest.raises(SystemExit):
        _parse(["--config", str(FRICTION_OVERLAY), "--out", str(tmp_path)])
    assert "randomizes the simulated joint friction" in capsys.readouterr().err
    args = _parse(["--config", str(CONFIG / "gear_learn.yaml"), "--out", str(tmp_path)])
    assert args.config.name == "gear_learn.yaml"
