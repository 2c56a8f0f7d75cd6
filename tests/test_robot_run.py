"""``run_robot`` (make run-franka): the commands it starts, its checks, its progress lines. The run
itself against franky-sim is tests/test_franka_ros.py's learning test and the command in docs/hardware.md."""

from __future__ import annotations

import io

import pytest

from nf_bringup.robot_run import FRANKY_GOAL, Progress, _parse, robot_commands


def _value(argv: list[str], key: str) -> str:
    return next(a.split(":=", 1)[1] for a in argv if a.startswith(key + ":="))


def test_franky_gets_the_cells_goal_once_for_both_nodes(tmp_path):
    args = _parse(["--out", str(tmp_path)])
    cmds = robot_commands(args, tmp_path, record=True)
    goal = "[" + ",".join(repr(float(v)) for v in FRANKY_GOAL) + "]"
    assert _value(cmds["arm"], "franka_driver:goal") == _value(cmds["learner"], "learner_node:goal") == goal
    assert _value(cmds["arm"], "franka_driver:robot_ip") == "127.0.0.1"
    assert _value(cmds["arm"], "franka_driver:automatic_error_recovery") == "true"
    assert _value(cmds["learner"], "learner_node:on_safe_hold") == "auto"
    assert _value(cmds["learner"], "learner_node:policy_subscribers") == "2" and "recorder" in cmds


def test_a_real_arm_needs_a_measured_goal_and_waits_for_a_person(tmp_path, capsys):
    with pytest.raises(SystemExit):
        _parse(["--robot", "172.16.0.2"])
    assert "needs --goal" in capsys.readouterr().err
    args = _parse(["--robot", "172.16.0.2", "--goal", "0.4", "0.1", "0.06"])
    cmds = robot_commands(args, tmp_path, record=False)
    assert _value(cmds["arm"], "franka_driver:robot_ip") == "172.16.0.2"
    assert not any("realtime" in a or "automatic_error_recovery" in a for a in cmds["arm"])  # the file's: enforce
    assert _value(cmds["learner"], "learner_node:on_safe_hold") == "wait"
    assert _value(cmds["learner"], "learner_node:goal") == "[0.4,0.1,0.06]"


def test_progress_says_the_time_left():
    out = io.StringIO()
    progress = Progress(out)
    line = "[learner] iteration   {}/20  return -1.0  success 0.00  final distance 0.03 m  sigma 1.00  rollouts 96.0 s"
    progress(line.format(1))
    assert "iteration 1/20: 96 s per iteration, about 30 min left" in out.getvalue()
    progress("[learner] prior: 1 of 1 rollouts not done yet")  # not an iteration line
    assert out.getvalue().count("\n") == 1
