"""Many arms in ``make run`` and the bag tools, without ROS: the runner's commands for ``--arms``, the
per-arm lines of summary.md, and a two-arm bag (the sample bag's messages under /arm0 and /arm1, so
both arms have the same episode ids) listed by ``nf_bags.info`` and grouped per arm by the reader.
The run itself: ``make run ARGS="--arms 2 --iterations 2"`` (docs/nodes.md, Many arms)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import yaml
from nf_bags import bagfile, info, reader
from nf_bags.writer import BagWriter

from nf_bringup.run_summary import arm_lines
from nf_bringup.stack import node_commands, policy_ready, recorder_ready

from ros_testing import REPO

SAMPLE = REPO / "bags" / "sample"
CONFIG = REPO / "config" / "gear_learn.yaml"
FILES = [str(REPO / "config" / "sim.yaml"), str(CONFIG)]  # the simulated stack's settings, then the task's


def _after(argv: list[str], flag: str) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == flag]


def test_without_arms_the_commands_are_the_single_arm_ones(tmp_path):
    cmds = node_commands([CONFIG], tmp_path, 3)
    assert set(cmds) == {"arm", "state", "learner", "recorder"}
    assert cmds["state"][1:3] == ["-m", "nf_bringup.robot_state"]  # the cell's description and transforms
    assert cmds["arm"] == [sys.executable, "-m", "nf_bringup.sim_stack", "--ros-args", "--params-file", FILES[0],
                           "--params-file", FILES[1]]
    assert not any("learner_node:arms" in a for a in cmds["learner"])
    assert "learner_node:iterations:=3" in cmds["learner"]
    assert not any("iterations" in a for a in node_commands([CONFIG], tmp_path)["learner"])  # the file's
    lockstep = yaml.safe_load(Path(FILES[0]).read_text())["/**/nf_controller"]["ros__parameters"]
    assert lockstep["idle_mode"] == "pause" and lockstep["max_consecutive_misses"] == 0
    assert recorder_ready([""]) == ("recording /joint_states (", "recording /effort_controller/commands (",
                                    "recording /rollouts (")


def test_arms_get_a_namespace_the_lockstep_file_and_the_learner_their_names(tmp_path):
    cmds = node_commands([CONFIG], tmp_path, 2, arms=3)
    assert set(cmds) == {"arm0", "arm1", "arm2", "arm0-state", "arm1-state", "arm2-state", "learner", "recorder"}
    assert _after(cmds["arm2-state"], "-r") == ["__ns:=/arm2"]
    for i in range(3):
        argv = cmds[f"arm{i}"]
        assert argv[1:3] == ["-m", "nf_bringup.sim_stack"]
        assert _after(argv, "-r") == [f"__ns:=/arm{i}"]
        # the lockstep settings reach a namespaced node through config/sim.yaml's /**/nf_controller section
        assert _after(argv, "--params-file") == FILES
        assert "-p" not in argv
    learner = cmds["learner"]
    assert "learner_node:arms:=['/arm0','/arm1','/arm2']" in learner
    assert "learner_node:policy_subscribers:=2" in learner  # per arm: its controller and the recorder
    assert cmds["recorder"][1:3] == ["-m", "nf_bags.record"] and "--topics" not in cmds["recorder"]  # all topics
    ready = recorder_ready(["/arm0", "/arm1", "/arm2"])
    assert len(ready) == 9 and "recording /arm2/rollouts (" in ready
    assert policy_ready(["/arm0", "/arm1"]) == ("recording /arm0/policy_parameters (",
                                                "recording /arm1/policy_parameters (")
    separate = node_commands([CONFIG], tmp_path, 2, composed=False, arms=2)
    assert set(separate) == {"arm0-sim", "arm0-controller", "arm0-state", "arm1-sim", "arm1-controller", "arm1-state",
                             "learner", "recorder"}
    assert _after(separate["arm1-sim"], "-r") == ["__ns:=/arm1"]


def test_a_resimulable_run_gives_every_sim_every_step_and_nothing_else(tmp_path):
    every = "sim_bridge:monitor_period:=0.0"
    for composed in (True, False):
        cmds = node_commands([CONFIG], tmp_path, 2, composed=composed, arms=2, resimulable=True)
        sims = {n for n, argv in cmds.items() if argv[2] in ("nf_bringup.sim_stack", "sim_bridge_node.node")}
        assert len(sims) == 2 and all(_after(cmds[n], "-p") == [every] for n in sims), cmds
        assert not any(every in argv for n, argv in cmds.items() if n not in sims)
    assert not any(every in argv for argv in node_commands([CONFIG], tmp_path, 2).values())
    # the file's own setting that this overrides (config/sim.yaml thins them)
    sim = yaml.safe_load(Path(FILES[0]).read_text())["/**/sim_bridge"]["ros__parameters"]
    assert sim["monitor_period"] > 0.0


def test_summary_lists_rollouts_per_arm_and_what_ran_again(tmp_path):
    arms_json = tmp_path / "arms.json"
    arms_json.write_text(json.dumps({"arms": {"/arm0": {"done": 9, "lost": 1, "late": 1},
                                              "/arm1": {"done": 7, "failed": 1}}, "batches": []}))
    text = "\n".join(arm_lines(arms_json, started=2))
    assert "2 arms ran rollouts (2 started); 2 dispatches ran again elsewhere" in text
    assert "| /arm0 | 9 | 1 | 0 | 1 |" in text and "| /arm1 | 7 | 0 | 1 | 0 |" in text
    assert arm_lines(tmp_path / "missing.json") == []


def two_arm_bag(path: Path) -> Path:
    """The sample bag's arm topics twice, under /arm0 and /arm1 (the same episode ids on both)."""
    writer = BagWriter(path)
    for raw in bagfile.iter_raw(SAMPLE):
        for ns in ("/arm0", "/arm1"):
            topic = ns + raw.topic if reader.arm_of(raw.topic) else raw.topic
            if topic not in writer.topics:
                writer.add_topic(topic, raw.type, raw.schema.data.decode())
            writer.write(topic, raw.data, raw.log_time)
    writer.close()
    return path


def test_bag_tools_list_the_arms_and_group_rollouts_per_arm(tmp_path, capsys):
    bag = two_arm_bag(tmp_path / "bag")
    assert reader.arms(bag) == ["/arm0", "/arm1"] and reader.arms(SAMPLE) == ["/"]
    one = reader.rollout_chunks(SAMPLE)
    grouped = reader.arm_rollout_chunks(bag)
    assert sorted(grouped) == sorted((arm, e) for arm in ("/arm0", "/arm1") for e in one)  # ids collide
    for (_, episode), chunks in grouped.items():
        assert [c.seq for c in chunks] == [c.seq for c in one[episode]]
    assert reader.rollout_chunks(bag, reader.arm_topic("/arm1", reader.ROLLOUTS)).keys() == one.keys()
    records = reader.episode_records(bag)
    assert len(records) == 2 * len(one)
    summary = reader.summarize(bag)
    assert summary["arms"] == ["/arm0", "/arm1"] and "resets" not in summary
    assert summary["per_arm"]["/arm1"] == {k: reader.summarize(SAMPLE)[k] for k in ("sim_seconds", "states", "resets")}
    assert [e["arm"] for e in summary["episodes"]] == ["/arm0", "/arm1"] * len(one)
    assert len(summary["policy_versions"]) == 2
    assert info.main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert "arms: 2: /arm0 (6 topics, " in out and "/arm1 (6 topics, " in out
    assert info.main([str(bag), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["arms"] == ["/arm0", "/arm1"]
