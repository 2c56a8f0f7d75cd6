"""`make run`'s process runner end to end: sim, controller, learner and bag recorder as separate
processes over real DDS, one short PPO iteration, and the run folder a user gets."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from nf_bags import bagfile, reader

from ros_testing import REPO, allocate_domain_id, ros_env

pytestmark = pytest.mark.ros


def test_stack_runs_an_iteration_and_leaves_a_complete_run_folder(tmp_path):
    run = tmp_path / "run"
    domain = allocate_domain_id()
    learner_args = ["-p", "learner_node:rollouts_per_iter:=2", "-p", "learner_node:eval_episodes:=1",
                    "-p", "episode_seconds:=0.5"]
    cmd = [sys.executable, "-m", "learner_node.stack", "--config", str(REPO / "config" / "gear.yaml"),
           "--iterations", "1", "--out", str(run), "--domain-id", str(domain),
           *[f"--learner-arg={a}" for a in learner_args]]
    done = subprocess.run(cmd, env=ros_env(domain), capture_output=True, text=True, timeout=400, cwd=tmp_path)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    # logs are forwarded with a prefix per process, and kept per process
    for name in ("sim", "controller", "learner", "recorder"):
        assert f"[{name}" in out, name
        assert (run / "logs" / f"{name}.log").stat().st_size > 0
    metrics = json.loads((run / "learner" / "metrics.json").read_text())
    assert [r["iteration"] for r in metrics] == [1]
    assert (run / "learner" / "checkpoint.pt").exists()
    assert (run / "learning_curves.png").stat().st_size > 10_000
    assert (run / "final_policy.gif").stat().st_size > 10_000
    summary = (run / "summary.md").read_text()
    assert "| 1 |" in summary and "Bag `bag/` (closed" in summary
    # the bag holds the run: closed cleanly, the two rollouts streamed by the controller, the policy
    health = bagfile.scan(run / "bag")
    assert health.closed and not health.lost
    for topic in ("/joint_states", "/effort_controller/commands", "/rollouts", "/policy_parameters"):
        assert health.counts[topic] > 0, (topic, dict(health.counts))
    episodes = reader.rollout_chunks(run / "bag")
    assert len(episodes) >= 3  # 2 training episodes + 1 evaluation episode
