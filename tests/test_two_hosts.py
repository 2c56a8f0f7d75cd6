"""Learner on one machine, arms on another: two network namespaces joined by a veth pair stand in
for two hosts; DDS discovers over the subnet with static unicast peers, as a user configures two
machines. Two namespaced arms on the arm host learn what the in-process trainer learns, as on one host."""

from __future__ import annotations

import json

import pytest
from test_learning_over_ros import CONFIG, SHORT, assert_same_learning, in_process_history
from test_many_arms import LOCKSTEP

from nf_bringup.testing.hosts import NetnsUnavailableError, TwoHosts

from ros_testing import RosProcess, allocate_domain_id


@pytest.fixture
def hosts():
    try:
        with TwoHosts() as two:
            yield two
    except NetnsUnavailableError as exc:
        pytest.skip(f"no network namespaces on this machine: {exc}")


def test_learner_and_two_arms_on_two_hosts_learn_as_on_one(tmp_path, hosts):
    domain = allocate_domain_id()
    lockstep = tmp_path / "lockstep.yaml"
    lockstep.write_text(LOCKSTEP)
    arms = [RosProcess(["-m", "nf_bringup.sim_stack", "--ros-args", "--params-file", CONFIG, "--params-file",
                        str(lockstep), "-r", f"__ns:={ns}"], domain, tmp_path / f"{ns[1:]}.log",
                       prefix=hosts.prefix("b"), peers=hosts.peers("b")) for ns in ("/arm0", "/arm1")]
    args = ["-m", "learner_node.node", "--ros-args", "--params-file", CONFIG, "-p", "learner_node:on_safe_hold:=auto",
            "-p", f"learner_node:out_dir:={tmp_path / 'run'}", "-p", "learner_node:iterations:=2",
            "-p", "learner_node:arms:=['/arm0','/arm1']"]
    for key, value in SHORT.items():
        args += ["-p", f"learner_node:{key}:={value}" if key != "episode_seconds" else f"{key}:={value}"]
    learner = RosProcess(args, domain, tmp_path / "learner.log", prefix=hosts.prefix("a"), peers=hosts.peers("a"))
    try:
        learner.proc.wait(240)
        assert learner.proc.returncode == 0, learner.log() + "".join(a.log() for a in arms)
    finally:
        learner.stop()
        for arm in arms:
            arm.stop()
    over_two_hosts = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert all(r["dropped_episodes"] == 0 for r in over_two_hosts)
    assert_same_learning(over_two_hosts, in_process_history(2, SHORT))
    used = json.loads((tmp_path / "run" / "arms.json").read_text())
    assert set(used["arms"]) == {"/arm0", "/arm1"}, used["arms"]  # both arms across the link ran rollouts


def test_without_peers_the_hosts_do_not_find_each_other(tmp_path, hosts):
    """The control: loopback-only discovery (the default) does not cross to the other host."""
    domain = allocate_domain_id()
    arm = RosProcess(["-m", "nf_bringup.sim_stack", "--ros-args", "--params-file", CONFIG], domain,
                     tmp_path / "arm.log", prefix=hosts.prefix("b"))
    learner = RosProcess(["-m", "learner_node.node", "--ros-args", "--params-file", CONFIG,
                          "-p", "learner_node:server_timeout:=5.0", "-p", f"learner_node:out_dir:={tmp_path / 'run'}"],
                         domain, tmp_path / "learner.log", prefix=hosts.prefix("a"))
    try:
        learner.proc.wait(120)
        assert learner.proc.returncode == 1 and "no run_episode action server" in learner.log(), learner.log()
    finally:
        learner.stop()
        arm.stop()
