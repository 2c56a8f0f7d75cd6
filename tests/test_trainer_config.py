"""TrainConfig: task defaults, clear errors for bad values, the per-task YAML files, overrides."""

from __future__ import annotations

import array
import math
from pathlib import Path

import numpy as np
import pytest

from learner_node.config import TrainConfig, parse_value, read_yaml_params

CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"


def test_task_defaults_follow_the_paper():
    gear = TrainConfig(task="gear")
    assert (gear.n_flow, gear.n_hidden, gear.sigma_init, gear.stiffness, gear.damping) == (1, 16, 5.0, 4.0, 1.0)
    assert gear.dim == 3 and gear.episode_seconds == 5.0
    block = TrainConfig(task="block")
    assert (block.n_flow, block.n_hidden, block.sigma_init, block.dim) == (2, 8, 2.0, 2)
    assert block.steps_per_decision == 10 and block.decisions_per_episode == 400
    assert TrainConfig(task="peg", sigma_init=3.0).sigma_init == 3.0  # explicit values win


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"task": "car"}, "unknown task .car.: give a built-in task"),
        ({"policy": "lstm"}, "policy must be one of"),
        ({"sigma_init": -1.0}, "sigma_init must be > 0"),
        ({"sigma_init": "abc"}, "sigma_init must be float"),
        ({"iterations": True}, "iterations must be int"),
        ({"iterations": 0}, "iterations must be in"),
        ({"rollouts_per_iter": 0}, "rollouts_per_iter must be in"),
        ({"seed": -1}, "seed must be in"),
        ({"decision_period": 0.0015}, "whole multiple of the 1 ms physics step"),
        ({"decision_period": 0.0}, "decision_period must be > 0"),
        ({"episode_seconds": 1.005}, "whole multiple of decision_period"),
        ({"episode_seconds": float("inf")}, "must be finite"),
        ({"clip_coef": 1.5}, "clip_coef must be in"),
        ({"gamma": 1.2}, "gamma must be in"),
        ({"gae_lambda": -0.1}, "gae_lambda must be in"),
        ({"learning_rate": 0.0}, "learning_rate must be > 0"),
        ({"minibatch_size": 0}, "minibatch_size must be in"),
        ({"n_flow": 0}, "n_flow must be in"),
        ({"param_elite": "succeeded"}, "param_elite must be one of"),
        ({"flow_init": "zeros"}, "flow_init must be one of"),
        ({"start": "sometimes"}, "start must be one of"),
        ({"stiffness": 0.0}, "stiffness must be > 0"),
        ({"eval_every": -1}, "eval_every must be in"),
    ],
)
def test_bad_values_give_clear_errors(overrides, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**overrides)


@pytest.mark.parametrize("task", ["gear", "peg", "block"])
def test_task_yaml_files_load(task):
    cfg = TrainConfig.from_sources(CONFIG_DIR / f"{task}.yaml")
    assert cfg.task == task
    # the files hold the paper's defaults, except the gains (each YAML file says why)
    gains = {"gear": {"sigma_init": 1.0, "stiffness": 300.0, "stiffness_axial": 60.0, "damping": 40.0},
             "peg": {"stiffness": 300.0, "stiffness_axial": 60.0, "damping": 40.0},
             "block": {"stiffness": 100.0, "damping": 20.0, "flow_init": "identity"}}[task]
    assert cfg == TrainConfig(task=task, **gains)


def test_yaml_sections_and_precedence(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(
        "/**:\n  ros__parameters:\n    task: block\n    sigma_init: 3.0\n    some_sim_setting: 7\n"
        "learner_node:\n  ros__parameters:\n    sigma_init: 4.0\n    learning_rate: 1e-3\n"
    )
    assert read_yaml_params(path) == {"task": "block", "sigma_init": 4.0, "learning_rate": "1e-3"}
    cfg = TrainConfig.from_sources(path, {"seed": "5", "iterations": 3})
    assert (cfg.task, cfg.sigma_init, cfg.learning_rate, cfg.seed, cfg.iterations) == ("block", 4.0, 1e-3, 5, 3)
    assert TrainConfig.from_sources(path, {"sigma_init": "0.5"}).sigma_init == 0.5  # CLI beats YAML


def test_yaml_errors_are_clear(tmp_path):
    bad_key = tmp_path / "k.yaml"
    bad_key.write_text("learner_node:\n  ros__parameters:\n    learning_rat: 0.1\n")
    with pytest.raises(ValueError, match="unknown learner_node parameter 'learning_rat'"):
        read_yaml_params(bad_key)
    no_params = tmp_path / "n.yaml"
    no_params.write_text("learner_node:\n  seed: 1\n")
    with pytest.raises(ValueError, match="ros__parameters"):
        read_yaml_params(no_params)
    with pytest.raises(ValueError, match="cannot read config"):
        read_yaml_params(tmp_path / "missing.yaml")
    with pytest.raises(ValueError, match="unknown setting 'sigma'"):
        TrainConfig.from_sources(None, {"sigma": "1"})
    with pytest.raises(ValueError, match="seed: expected int"):
        parse_value("seed", "1.5")


def test_none_resets_to_task_default_and_table_lists_every_field():
    cfg = TrainConfig.from_sources(None, {"task": "peg", "sigma_init": "none"})
    assert cfg.sigma_init == 1.0
    table = cfg.table()
    for name in cfg.to_dict():
        assert f"| {name} " in table


def test_overlays_layer_over_the_task_file_and_later_files_win():
    """An overlay (a short file after the task file) changes only what it names."""
    learn = TrainConfig.from_sources(CONFIG_DIR / "gear_learn.yaml")
    arm = TrainConfig.from_sources([CONFIG_DIR / "gear_learn.yaml", CONFIG_DIR / "franka_learn.yaml"])
    friction = TrainConfig.from_sources([CONFIG_DIR / "gear_learn.yaml", CONFIG_DIR / "friction.yaml"])
    changed = {k for k, v in arm.to_dict().items() if learn.to_dict()[k] != v}
    assert changed == {"param_elite", "param_sigma_jump", "param_sigma_gains", "param_settle_rule",
                       "param_sigma_settle"}
    changed = {k for k, v in friction.to_dict().items() if learn.to_dict()[k] != v}
    assert changed == {"friction_coulomb", "friction_viscous", "potential_force_bound"}
    assert learn.iterations == 30  # make run's
    assert learn.stiffness_matrix().tolist() == [[300.0, 0.0, 0.0], [0.0, 300.0, 0.0], [0.0, 0.0, 300.0]]


def test_a_stored_run_with_a_removed_setting_is_read_when_it_used_what_is_now_plain():
    stored = {**TrainConfig(task="gear").to_dict(), "adv_norm": "standardize", "param_ratio": "joint",
              "exploration": "action"}
    assert "adv_norm" not in TrainConfig.with_defaults(stored)
    with pytest.raises(ValueError, match=r"removed settings.*adv_norm='center'"):
        TrainConfig.with_defaults({**stored, "adv_norm": "center"})


def test_goal_sets_the_policys_x_ref_and_the_reward_goal():
    """A goal measured on a real cell (``goal``) replaces the simulated task's: the policy the learner
    publishes carries it as x_ref (the controller's reward goal too), and so does the in-process
    rollout's reward. From a command line, a ROS array parameter or a YAML list; bad ones refused."""
    from learner_node.trainer import Trainer

    default = Trainer(TrainConfig.from_sources(CONFIG_DIR / "gear_learn.yaml"))
    assert default.cfg.goal is None
    np.testing.assert_allclose(default.policy.to_params().x_ref, [0.5, 0.0, 0.07])
    for given in ("0.52,0.03,0.05", "[0.52, 0.03, 0.05]", [0.52, 0.03, 0.05], array.array("d", [0.52, 0.03, 0.05])):
        assert TrainConfig.from_sources(None, {"task": "gear", "goal": given}).goal == [0.52, 0.03, 0.05]
    trainer = Trainer(TrainConfig.from_sources(CONFIG_DIR / "gear_learn.yaml", {"goal": "0.52,0.03,0.05"}))
    np.testing.assert_allclose(trainer.policy.to_params().x_ref, [0.52, 0.03, 0.05])
    np.testing.assert_allclose(trainer.runner.episode_spec(None).x_goal, [0.52, 0.03, 0.05])
    for bad, message in (("0.5,0", "3 values"), ("a,b,c", "list of numbers"), ([0.5, 0.0, math.nan], "finite")):
        with pytest.raises(ValueError, match=message):
            TrainConfig.from_sources(None, {"task": "gear", "goal": bad})
