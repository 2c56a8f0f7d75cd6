"""Many arms, one learner, over real DDS: four composed lockstep sim stacks under /arm0../arm3, found
by the learner (not listed), run an iteration's rollouts at once and learn exactly what one arm (the
in-process trainer) learns; an arm killed with SIGKILL mid-episode costs that episode only, which runs
again elsewhere with the same seeds."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
import torch
from nf_msgs.msg import ControllerStatus

from learner_node.config import TrainConfig
from learner_node.trainer import Trainer, metrics_without_timing

from ros_testing import REPO, RosProcess, allocate_domain_id
from test_nodes import RELIABLE, Probe

pytestmark = pytest.mark.ros

TOL = 1e-9


LOCKSTEP = "/**/nf_controller:\n  ros__parameters:\n    idle_mode: pause\n    max_consecutive_misses: 0\n"


def arm_stack(domain: int, ns: str, config: str, tmp: Path) -> RosProcess:
    """A composed lockstep arm under ``ns`` ("": none). ``-p nf_controller:...`` only matches a node
    without a namespace, and a plain ``-p`` loses to the file's ``/**/nf_controller`` section: the
    controller's settings come in a second parameters file with the same section."""
    extra = tmp / "lockstep.yaml"
    extra.write_text(LOCKSTEP)
    remap = ["-r", f"__ns:={ns}"] if ns else []
    return RosProcess(["-m", "nf_bringup.sim_stack", "--ros-args", "--params-file", config, "--params-file",
                       str(extra), *remap], domain, tmp / f"{ns[1:] or 'arm'}.log")


def learner(domain: int, out: Path, log: Path, config: str, settings: dict) -> RosProcess:
    args = ["-m", "learner_node.node", "--ros-args", "--params-file", config, "-p", "learner_node:on_safe_hold:=auto",
            "-p", f"learner_node:out_dir:={out}"]
    for key, value in settings.items():
        args += ["-p", f"learner_node:{key}:={value}" if key != "episode_seconds" else f"{key}:={value}"]
    return RosProcess(args, domain, log)


def in_process(config: str, settings: dict) -> Trainer:
    trainer = Trainer(TrainConfig.from_sources(config, settings))
    for _ in range(settings["iterations"]):
        trainer.train_iteration()
    return trainer


def largest_difference(over_ros: list[dict], ref: list[dict]) -> float:
    """The largest relative difference of any learning metric (the trainer's, timing aside) between two
    histories (the learner adds how many arms ran and what ran again)."""
    assert [r["iteration"] for r in over_ros] == [r["iteration"] for r in ref]
    worst = 0.0
    for a, b in zip(over_ros, ref, strict=True):
        a, b = metrics_without_timing(a), metrics_without_timing(b)
        for key in set(b) - {"arms_used", "rerun_episodes", "dropped_episodes"}:
            worst = max(worst, abs(a[key] - b[key]) / max(1.0, abs(b[key])))
    return worst


def weights_difference(run: Path, trainer: Trainer) -> float:
    ckpt = torch.load(run / "checkpoint.pt", weights_only=True)
    mine = trainer.policy.state_dict()
    return max(float((ckpt["policy"][k].double() - v.double()).abs().max()) for k, v in mine.items())


def stop_all(procs: list[RosProcess]) -> None:
    for p in reversed(procs):
        p.stop()


def learn(tmp: Path, namespaces: list[str], config: str, settings: dict) -> Path:
    """A learner run against composed lockstep arms in ``namespaces``; its run folder."""
    tmp.mkdir()
    domain = allocate_domain_id()
    arms = [arm_stack(domain, ns, config, tmp) for ns in namespaces]
    try:
        lrn = learner(domain, tmp / "run", tmp / "learner.log", config, settings)
        lrn.proc.wait(180)
        assert lrn.proc.returncode == 0, lrn.log() + "\n".join(a.log() for a in arms)
    finally:
        stop_all(arms)
    return tmp / "run"


def test_four_arms_learn_what_one_arm_learns(tmp_path):
    config = str(REPO / "config" / "gear.yaml")
    settings = {"episode_seconds": 0.5, "rollouts_per_iter": 8, "eval_episodes": 0, "iterations": 2}
    one = learn(tmp_path / "one", [""], config, settings)
    four = learn(tmp_path / "four", [f"/arm{i}" for i in range(4)], config, settings)
    m1, m4 = (json.loads((r / "metrics.json").read_text()) for r in (one, four))
    w1, w4 = (torch.load(r / "checkpoint.pt", weights_only=True)["policy"] for r in (one, four))
    metrics_diff = largest_difference(m4, m1)
    weights_diff = max(float((w4[k] - w1[k]).abs().max()) for k in w1)
    ref = in_process(config, settings)
    vs_ref = largest_difference(m4, ref.history)
    print(f"4 arms vs 1 arm over ROS: largest relative metric difference {metrics_diff:.2e}, largest weight "
          f"difference {weights_diff:.2e}; vs the in-process trainer: metrics {vs_ref:.2e}, "
          f"weights {weights_difference(four, ref):.2e}")
    assert metrics_diff <= TOL and weights_diff <= TOL
    assert vs_ref <= 1e-6  # the controller sums some terms in another order
    assert all(r["dropped_episodes"] == 0 and r["rerun_episodes"] == 0 for r in m4)
    arms_log = json.loads((four / "arms.json").read_text())
    assert sum(c["done"] for c in arms_log["arms"].values()) == 16
    assert len(arms_log["arms"]) >= 2, arms_log["arms"]  # the work was spread, not run by one arm
    assert all(set(b["ran_on"]) <= {f"/arm{i}" for i in range(4)} for b in arms_log["batches"])
    assert set(json.loads((one / "arms.json").read_text())["arms"]) == {"/"}


def test_an_arm_killed_mid_episode_costs_one_episode_not_the_iteration(tmp_path):
    """Parameter exploration (a policy version per dispatched rollout): the lost rollout runs again on
    another arm under a new, larger version, and the update equals the in-process one."""
    config = str(REPO / "config" / "gear_learn.yaml")
    settings = {"episode_seconds": 1.0, "rollouts_per_iter": 8, "eval_episodes": 0, "iterations": 1}
    domain = allocate_domain_id()
    probe = Probe(domain)
    status = probe.collect(ControllerStatus, "/arm2/controller_status", RELIABLE)
    arms = [arm_stack(domain, f"/arm{i}", config, tmp_path) for i in range(4)]
    run = tmp_path / "run"
    try:
        # the probe hears arm2 before the learner starts: a fresh clone once finished arm2's only episode
        # while discovery still matched the probe, and the kill never came
        assert probe.spin_until(lambda: bool(status), 120), arms[2].log()
        lrn = learner(domain, run, tmp_path / "learner.log", config, {**settings, "arm_timeout": 3.0})
        running = ControllerStatus.MODE_RUNNING
        assert probe.spin_until(lambda: status and status[-1][1].mode == running, 120), lrn.log()
        arms[2].proc.send_signal(signal.SIGKILL)  # mid-episode: its status says it runs one
        arms[2].proc.wait(10)
        lrn.proc.wait(180)
        assert lrn.proc.returncode == 0, lrn.log()
    finally:
        stop_all(arms)
        probe.close()
    over_ros = json.loads((run / "metrics.json").read_text())
    arms_log = json.loads((run / "arms.json").read_text())
    batch = arms_log["batches"][-1]
    lost = [d for d in batch["dispatches"] if d["outcome"] == "lost"]
    assert [d["arm"] for d in lost] == ["/arm2"], batch["dispatches"]
    again = [d for d in batch["dispatches"] if d["rollout"] == lost[0]["rollout"] and d["outcome"] == "done"]
    assert len(again) == 1 and again[0]["arm"] != "/arm2"
    done = sorted(d["rollout"] for d in batch["dispatches"] if d["outcome"] == "done")
    assert done == list(range(8)) and batch["dropped"] == []  # every rollout once
    assert over_ros[0]["dropped_episodes"] == 0 and over_ros[0]["rerun_episodes"] == 1
    ref = in_process(config, settings)
    metrics_diff, weights_diff = largest_difference(over_ros, ref.history), weights_difference(run, ref)
    print(f"after the kill: largest relative metric difference {metrics_diff:.2e}, weights {weights_diff:.2e}")
    assert metrics_diff <= TOL and weights_diff <= TOL
    assert "arm /arm2 lost" in (tmp_path / "learner.log").read_text()
