"""`make run`'s process runner end to end: the composed arm (sim + controller in one process),
learner and bag recorder as separate processes over real DDS, one short PPO iteration, and the run
folder a user gets."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time

import pytest
from nf_bags import bagfile, reader

from nf_bringup.processes import ManagedProcess
from nf_bringup.stack import RECORDER_READY, wait_for_recorder

from ros_testing import REPO, allocate_domain_id, ros_env


def _printer(lines: str, then_sleep: float = 30.0) -> list[str]:
    """argv of a child that prints ``lines`` (with a pause before the last) and then lingers."""
    *head, last = lines.splitlines()
    code = (f"import time; print({chr(10).join(head)!r}, flush=True); time.sleep(0.5); print({last!r}, flush=True); "
            f"time.sleep({then_sleep})")
    return [sys.executable, "-c", code]


def test_the_learner_waits_for_the_recorder_to_subscribe_to_the_arm_and_rollout_topics(tmp_path):
    # not a ROS test: children that print what the recorder prints, the last topic after a pause
    lines = "\n".join(["recording all topics into x", "recording /joint_states (sensor_msgs/msg/JointState, reliable)",
                       "recording /effort_controller/commands (std_msgs/msg/Float64MultiArray, reliable)",
                       "recording /rollouts (nf_msgs/msg/RolloutChunk, reliable)"])
    recorder = ManagedProcess("recorder", _printer(lines), dict(os.environ), tmp_path, echo=False,
                              watch=RECORDER_READY)
    try:
        t0 = time.monotonic()
        assert wait_for_recorder(recorder, [], timeout=20.0)
        assert 0.4 < time.monotonic() - t0 < 15.0  # it waited for the last line, not for the timeout
    finally:
        recorder.stop(timeout=2.0)
    # /rollouts never comes: a bounded wait and a warning, not a hang
    partial = "\n".join(lines.splitlines()[:3])
    recorder = ManagedProcess("recorder", _printer(partial), dict(os.environ), tmp_path, echo=False,
                              watch=RECORDER_READY)
    try:
        t0 = time.monotonic()
        assert not wait_for_recorder(recorder, [], timeout=1.5)
        assert time.monotonic() - t0 < 10.0
    finally:
        recorder.stop(timeout=2.0)
    # a node of the stack exits while waiting: stop waiting at once
    recorder = ManagedProcess("recorder", _printer(partial), dict(os.environ), tmp_path, echo=False,
                              watch=RECORDER_READY)
    gone = ManagedProcess("controller", [sys.executable, "-c", "pass"], dict(os.environ), tmp_path, echo=False)
    try:
        t0 = time.monotonic()
        assert not wait_for_recorder(recorder, [gone], timeout=30.0)
        assert time.monotonic() - t0 < 15.0
    finally:
        recorder.stop(timeout=2.0)
        gone.stop(timeout=2.0)


@pytest.mark.ros
def test_stack_runs_an_iteration_and_leaves_a_complete_run_folder(tmp_path):
    run = tmp_path / "run"
    domain = allocate_domain_id()
    learner_args = ["-p", "learner_node:rollouts_per_iter:=2", "-p", "learner_node:eval_episodes:=1",
                    "-p", "learner_node:eval_every:=1", "-p", "episode_seconds:=0.5"]
    # make run's own command and task file (config/sim.yaml, then config/gear_learn.yaml), shortened
    cmd = [sys.executable, "-m", "nf_bringup.stack",
           "--iterations", "2", "--out", str(run), "--domain-id", str(domain),
           *[f"--learner-arg={a}" for a in learner_args]]
    done = subprocess.run(cmd, env=ros_env(domain), capture_output=True, text=True, timeout=400, cwd=REPO)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    # logs are forwarded with a prefix per process, and kept per process
    for name in ("arm", "learner", "recorder"):
        assert f"[{name}" in out, name
        assert (run / "logs" / f"{name}.log").stat().st_size > 0
    metrics = json.loads((run / "learner" / "metrics.json").read_text())
    assert [r["iteration"] for r in metrics] == [1, 2]
    assert (run / "learner" / "checkpoint.pt").exists()
    assert (run / "learning_curves.png").stat().st_size > 10_000
    assert (run / "final_policy.gif").stat().st_size > 10_000
    summary = (run / "summary.md").read_text()
    assert "| 1 |" in summary and "Bag `bag/` (closed" in summary
    # what was lost, refused or recovered, as the nodes last reported it: nothing in a clean run
    assert "nf_controller: control loop: deadline_misses" in summary and "faults 0, bad_inputs 0" in summary, summary
    assert "sim_bridge: driver: command_timeouts 0, bad_commands 0" in summary, summary
    # the prior evaluated on the same held-out start as the learned controller, both in the summary
    prior = json.loads((run / "learner" / "evaluation_prior.json").read_text())
    final = json.loads((run / "learner" / "evaluation.json").read_text())
    assert (prior["iteration"], final["iteration"]) == (0, 2) and prior["episodes"] == final["episodes"] == 1
    # the GIF is the evaluation's first held-out start, with the policy's law: it ends as that episode did
    video = re.search(r"video of the final policy: \S+ \(depth (-?[0-9.]+) mm, success (True|False)", out)
    assert video, out[-2000:]
    assert video.group(2) == str(final["per_episode"][0]["success"])
    assert [e["start_seed"] for e in prior["per_episode"]] == [e["start_seed"] for e in final["per_episode"]]
    assert "| the prior (before iteration 1) | 1 |" in summary and "| learned (after iteration 2) | 1 |" in summary
    # eval_every 1 over ROS: after iteration 1 between the iterations, after 2 the final evaluation itself
    at1 = json.loads((run / "learner" / "evaluations" / "iteration_0001.json").read_text())
    assert at1["iteration"] == 1 and at1["over_ros"]
    assert at1["per_episode"][0]["start_seed"] == final["per_episode"][0]["start_seed"]
    assert [r["eval_final_distance"] for r in metrics] == [at1["final_distance_mean"], final["final_distance_mean"]]
    # the update takes milliseconds: in seconds with one decimal it read 0.0 for every iteration
    assert f"| {1e3 * metrics[0]['update_seconds']:.0f} |" in summary and "update (ms)" in summary
    # the bag holds the run: closed cleanly, the two rollouts streamed by the controller, the policy
    health = bagfile.scan(run / "bag")
    assert health.closed and not health.lost
    for topic in ("/joint_states", "/effort_controller/commands", "/rollouts", "/policy_parameters"):
        assert health.counts[topic] > 0, (topic, dict(health.counts))
    # every episode, the first included (the learner starts only once the recorder subscribes), complete
    episodes = reader.rollout_chunks(run / "bag")
    # the prior's evaluation, 2 training rollouts, the evaluation after iteration 1, 2 rollouts, the final one
    assert len(episodes) == 7, {k: [(c.seq, c.final) for c in v] for k, v in episodes.items()}
    assert sorted(episodes) == list(range(min(episodes), min(episodes) + 7))
    assert all(v[-1].final and len(v) == v[-1].n_chunks for v in episodes.values())
