"""Task files (nf_core.task_spec, config/tasks/): one file gives the scene, the controller's model of the
held part, the goal, the seated pose and the success depth, and they agree; a file that cannot be right is
refused when it is loaded, with the reason."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from learner_node.config import TrainConfig
from nf_controller_node.arm_model import ArmModel
from nf_core.task_spec import BUILTIN_TASK_DIR, TaskFileError, held_part_inertia, load_task, part_from_text
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scenes import build_scene
from sim_bridge_node.scripted_insertion import HAND_DOWN, run_insertion

GEAR_FILE = BUILTIN_TASK_DIR / "gear.yaml"


def write_task(tmp_path: Path, change: dict, base: Path = GEAR_FILE, name: str = "mine.yaml") -> Path:
    """The built-in file ``base`` with ``change`` merged into it (one level of nesting), written to tmp_path."""
    data = yaml.safe_load(base.read_text())
    for key, value in change.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        elif value is None:
            data.pop(key, None)
        else:
            data[key] = value
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("task", ["gear", "peg", "gear_clamp"])
def test_builtin_start_joints_are_the_inverse_kinematics_of_the_files_start(task):
    spec = load_task(task)
    env = InsertionEnv(task)
    obs = env.reset()
    np.testing.assert_allclose(obs.x, spec.start_tcp, atol=2e-6)
    np.testing.assert_allclose(env.tcp_rotation, HAND_DOWN, atol=2e-6)
    assert env.data.ncon == 0


# A user's gear: a 35 mm bore onto a 32 mm shaft with a 40 mm shoulder, 25 mm thick, 0.2 kg, on a fixture
# 10 cm to the side and 2 cm higher, with slipperier contacts; the start is solved by inverse kinematics.
USER_GEAR = {
    "part": {"bore_radius": 0.0175, "outer_radius": 0.035, "thickness": 0.025, "mass": 0.2},
    "fixture": {"position": [0.45, 0.10, 0.11], "shaft_radius": 0.016, "shaft_length": 0.025,
                "shoulder_radius": 0.02},
    "friction": 0.25,
    "success_depth": 0.02,
    "start": {"height": 0.15, "joints": None},
}


@pytest.fixture(scope="module")
def user_gear(tmp_path_factory) -> Path:
    return write_task(tmp_path_factory.mktemp("task"), USER_GEAR)


def test_a_users_gear_file_gives_a_scene_model_goal_and_success_that_agree(user_gear):
    spec = load_task(user_gear)
    env = InsertionEnv(str(user_gear))
    m = env.model
    # the scene: the pin and the shoulder where and as large as the file says, the bore as the file says
    pin = m.geom("shaft_pin")
    top = m.body("shaft").pos + m.geom_pos[pin.id] + [0.0, 0.0, m.geom_size[pin.id][1]]
    np.testing.assert_allclose(top, [0.45, 0.10, 0.11], atol=1e-12)
    assert m.geom_size[pin.id][0] == pytest.approx(0.016) and 2 * m.geom_size[pin.id][1] == pytest.approx(0.025)
    assert m.geom("shaft_shoulder").size[0] == pytest.approx(0.02)
    seg = m.geom("gear_segment_0")
    assert np.hypot(*seg.pos[:2]) - seg.size[0] == pytest.approx(0.0175)
    assert 2 * seg.size[2] == pytest.approx(0.025)
    assert m.body("gear").mass[0] == pytest.approx(0.2)
    assert m.geom_friction[pin.id][0] == pytest.approx(0.25) and seg.friction[0] == pytest.approx(0.25)
    # the start: the file's height above the shaft, hand down, by inverse kinematics
    obs = env.reset()
    np.testing.assert_allclose(obs.x, [0.45, 0.10, 0.26], atol=2e-5)
    np.testing.assert_allclose(env.tcp_rotation, HAND_DOWN, atol=1e-4)
    # the controller's model of the part: the text a policy carries gives the scene's TCP and mass
    text = TrainConfig(task=str(user_gear)).held_part
    assert text.startswith("gear ") and "bore_radius=0.0175" in text
    arm = ArmModel(part=held_part_inertia(text))
    np.testing.assert_allclose(arm.tcp_position(obs.q), obs.x, atol=1e-6)
    assert part_from_text(text) == spec.part
    # the goal is the seated pose, and a scripted push down the axis seats the gear there, a success
    np.testing.assert_allclose(env.goal_position, [0.45, 0.10, 0.11 - 0.025], atol=1e-12)
    result = run_insertion(env, seconds=3.0)
    assert result["success"] and result["depth"] >= 0.024, result
    np.testing.assert_allclose(result["x"], env.goal_position, atol=0.0015)
    assert env.scene.success_depth == 0.02


def test_a_users_peg_file_builds_its_hole_and_seats(tmp_path):
    path = write_task(tmp_path, {"part": {"radius": 0.008, "length": 0.05}, "fixture": {"hole_half_width": 0.0095,
                                                                                       "hole_depth": 0.015},
                                 "success_depth": 0.012, "start": {"joints": None}},
                      base=BUILTIN_TASK_DIR / "peg.yaml")
    env = InsertionEnv(str(path))
    assert env.scene.kind == "peg"
    assert env.model.geom("peg_cylinder").size[0] == pytest.approx(0.008)
    env.reset()
    result = run_insertion(env, seconds=3.0)
    assert result["success"] and result["depth"] >= 0.014, result


@pytest.mark.parametrize(("change", "reason"), [
    ({"part": {"bore_radius": 0.013}}, "the bore .* is not larger than the shaft"),
    ({"part": {"outer_radius": 0.012}}, "outer radius .* is not larger than its bore"),
    ({"fixture": {"shoulder_radius": 0.015}}, "nothing for the gear to seat on"),
    ({"fixture": {"position": [1.3, 0.0, 0.09]}}, "beyond the arm's reach"),
    ({"fixture": {"position": [0.05, 0.0, 0.09]}}, "inside the arm's own footprint"),
    ({"start": {"height": 0.0}}, "would start inside the fixture"),
    ({"success_depth": 0.03}, "deeper than the part can go"),
    ({"part": {"mass": -1.0}}, "mass must be > 0"),
    ({"friction": 3.0}, "not a sliding friction coefficient"),
    ({"fixture": {"postion": [0.5, 0.0, 0.09]}}, r"unknown key\(s\) \['postion'\]"),
    ({"fixture": {"position": [0.5, 0.0]}}, "position must be 3 finite numbers"),
    ({"part": {"kind": "bolt"}}, "kind must be one of"),
    ({"randomise": {"fixture_position": [0.05, 0.0, 0.0]}}, r"half-ranges must be in \[0, 0.02\] m"),
    ({"randomise": {"friction": [0.6, 0.3]}}, "friction must be a range"),
])
def test_a_file_that_cannot_be_right_is_refused_with_the_reason(tmp_path, change, reason):
    with pytest.raises(TaskFileError, match=reason):
        load_task(write_task(tmp_path, change))


@pytest.mark.parametrize(("change", "reason"), [
    ({"part": {"radius": 0.013}}, "does not fit the hole"),
    ({"part": {"length": 0.015}}, "not longer than the hole is deep"),
    ({"part": {"radius": 0.0}}, "radius must be > 0"),
    ({"part": {"bore_radius": 0.01}}, "bore_radius is a gear's"),
])
def test_a_peg_file_that_cannot_be_right_is_refused_with_the_reason(tmp_path, change, reason):
    with pytest.raises(TaskFileError, match=reason):
        load_task(write_task(tmp_path, change, base=BUILTIN_TASK_DIR / "peg.yaml"))


def test_a_start_out_of_reach_is_refused_when_the_scene_is_built(tmp_path):
    path = write_task(tmp_path, {"start": {"tcp": [0.9, 0.0, 0.6], "joints": None}})
    with pytest.raises(TaskFileError, match="out of the arm's reach"):
        build_scene(str(path))


def test_unknown_tasks_and_missing_files_name_the_choices(tmp_path):
    with pytest.raises(TaskFileError, match=r"unknown task 'anvil'.*gear.*peg"):
        load_task("anvil")
    with pytest.raises(TaskFileError, match="not found"):
        load_task(tmp_path / "nothing.yaml")
    with pytest.raises(ValueError, match="unknown task 'anvil'"):
        TrainConfig(task="anvil")
    bad = tmp_path / "bad.yaml"
    bad.write_text("part: [1, 2\n")
    with pytest.raises(TaskFileError, match="not valid YAML"):
        load_task(bad)


def test_the_builtin_files_are_the_built_in_parts_and_scenes():
    assert load_task("gear").part.text() == "gear" and load_task("peg").part.text() == "peg"
    assert part_from_text("none") is None
    for bad in ("anvil", "gear bore_radius=x", "gear bore=0.02"):
        with pytest.raises(TaskFileError):
            part_from_text(bad)
    # the clamp task's jaw is there; the gear task has none
    assert mujoco.mj_name2id(build_scene("gear_clamp").model, mujoco.mjtObj.mjOBJ_GEOM, "clamp_jaw") >= 0
    assert mujoco.mj_name2id(build_scene("gear").model, mujoco.mjtObj.mjOBJ_GEOM, "clamp_jaw") == -1


def test_randomise_varies_the_cell_per_episode_seed_and_keeps_what_the_controller_is_told(tmp_path):
    path = write_task(tmp_path, {"randomise": {"fixture_position": [0.003, 0.003, 0.002], "friction": [0.3, 0.6],
                                               "part_mass": [0.1, 0.15]}})
    env = InsertionEnv(str(path))
    m = env.model
    pin, gear, seg = m.geom("shaft_pin").id, m.body("gear").id, m.geom("gear_segment_0").id
    env.reset()  # the fixed start: the file's nominal cell
    pin0, goal = env.data.geom_xpos[pin].copy(), env.goal_position
    assert not env.episode_task.fixture_offset.any() and m.body_mass[gear] == pytest.approx(0.12)
    draws = {}
    for seed in (5, 6, 5):
        env.reset(seed)
        d = env.episode_task
        np.testing.assert_allclose(env.data.geom_xpos[pin], pin0 + d.fixture_offset, atol=1e-12)
        assert m.geom_friction[pin, 0] == m.geom_friction[seg, 0] == d.friction and 0.3 <= d.friction <= 0.6
        assert m.body_mass[gear] == pytest.approx(d.part_mass) and 0.1 <= d.part_mass <= 0.15
        assert np.all(np.abs(d.fixture_offset) <= [0.003, 0.003, 0.002]) and d.fixture_offset.any()
        np.testing.assert_array_equal(env.goal_position, goal)  # the controller is told the nominal cell
        draws.setdefault(seed, []).append((tuple(d.fixture_offset), d.friction, d.part_mass))
    assert draws[5][0] == draws[5][1] and draws[5][0] != draws[6][0]
    # success is measured on the fixture where it is: a push down the moved axis seats the gear
    env.reset(5)
    result = run_insertion(env, offset=env.episode_task.fixture_offset, seconds=3.0)
    assert result["success"] and result["depth"] >= 0.019, result


def test_a_users_part_is_learned_in_process_and_only_a_controller_holding_it_takes_the_policy(user_gear):
    """The learner's own rollouts run a controller whose held part is the file's; the policy's law names it,
    a controller holding that part installs the policy and one holding the gear task's gear refuses it."""
    from learner_node.trainer import Trainer
    from nf_controller_node.control_loop import ControlLoop, PolicyParameterError

    cfg = TrainConfig.from_sources(BUILTIN_TASK_DIR.parent / "gear_learn.yaml",
                                   {"task": str(user_gear), "iterations": 1, "rollouts_per_iter": 2,
                                    "episode_seconds": 0.1, "eval_episodes": 1})
    trainer = Trainer(cfg)
    metrics = trainer.train_iteration()
    assert metrics["faults"] == 0.0 and trainer.runner.arm.held_part == cfg.held_part != "gear"
    params = trainer.policy.to_params(version=1)
    assert params.law.held_part == cfg.held_part
    ControlLoop(ArmModel(part=held_part_inertia(cfg.held_part))).prepare_policy(params)
    with pytest.raises(PolicyParameterError, match=r"learned with held_part 'gear bore_radius=0\.0175"):
        ControlLoop(ArmModel(part=held_part_inertia("gear"))).prepare_policy(params)


def test_a_checkpoint_keeps_its_task_file_for_a_machine_that_does_not_have_it(tmp_path, monkeypatch):
    """A policy trained on a user's file is deployed elsewhere (the robot's PC): the checkpoint carries the
    file's text, and its settings read back with the same cell where the file is gone."""
    import torch

    from learner_node.trainer import Trainer

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    task = write_task(tmp_path, USER_GEAR, name="bench_gear.yaml")
    cfg = TrainConfig.from_sources(BUILTIN_TASK_DIR.parent / "gear_learn.yaml",
                                   {"task": str(task), "iterations": 1, "rollouts_per_iter": 2,
                                    "episode_seconds": 0.1, "eval_episodes": 1})
    Trainer(cfg).save_checkpoint(tmp_path / "checkpoint.pt")
    part = load_task(task).part.text()
    task.unlink()
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    again = TrainConfig(**TrainConfig.with_defaults(state["config"]))
    assert again.held_part == part and Path(again.task).parent == tmp_path / "cache" / "nf-control" / "tasks"
    np.testing.assert_array_equal(load_task(again.task).goal_position, [0.45, 0.10, 0.11 - 0.025])
    # a built-in task stores no copy
    assert "task_file" not in TrainConfig(task="gear").stored()
