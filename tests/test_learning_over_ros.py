"""The whole stack over real DDS: PPO iterations through the run_episode action and the streamed
rollouts (equal to the in-process trainer) with the sim and the controller composed in one process
(``nf_sim_stack``) and as two processes, a learner killed mid-iteration and resumed from its
checkpoint, and the controller unchanged against a hardware-like driver."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus, RolloutChunk
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.action import ActionClient
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from learner_node.config import TrainConfig
from learner_node.flow import rescale_flow_weights
from learner_node.trainer import CHECKPOINT_FORMAT, Trainer, build_policy, metrics_without_timing
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import MODE_IDLE, JointMap
from nf_core import panda_spec, qos
from nf_core.policy_params import PolicyParameters
from nf_core.topics import POLICY_PARAMETERS

from ros_testing import REPO, RosProcess, allocate_domain_id
from test_nodes import RELIABLE, Probe, policy_msg

pytestmark = pytest.mark.ros

CONFIG = str(REPO / "config" / "gear.yaml")
SHORT = {"episode_seconds": 0.5, "rollouts_per_iter": 3, "eval_episodes": 0}


def stack(domain: int, tmp: Path, idle_mode: str, composed: bool = True, config: str = CONFIG,
          extra: tuple[str, ...] = ()) -> list[RosProcess]:
    """The arm and its controller: one composed process, or the sim and the controller apart."""
    ctl_args = ["-p", f"nf_controller:idle_mode:={idle_mode}", "-p", "nf_controller:max_consecutive_misses:=0",
                *extra]
    if composed:
        return [RosProcess(["-m", "nf_bringup.sim_stack", "--ros-args", "--params-file", config, *ctl_args],
                           domain, tmp / "composed.log")]
    sim = RosProcess(["-m", "sim_bridge_node.node", "--ros-args", "--params-file", config], domain, tmp / "sim.log")
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "--params-file", config, *ctl_args],
                     domain, tmp / "controller.log")
    return [sim, ctl]


def logs(procs: list[RosProcess]) -> str:
    return "\n".join(p.log() for p in procs)


def stop(procs: list[RosProcess]) -> None:
    for p in reversed(procs):
        p.stop()


def learner(domain: int, out: Path, log: Path, iterations: int, settings: dict, config: str = CONFIG) -> RosProcess:
    args = ["-m", "learner_node.node", "--ros-args", "--params-file", config, "-p", "learner_node:on_safe_hold:=auto",
            "-p", f"learner_node:out_dir:={out}", "-p", f"learner_node:iterations:={iterations}"]
    for key, value in settings.items():
        args += ["-p", f"learner_node:{key}:={value}" if key != "episode_seconds" else f"{key}:={value}"]
    return RosProcess(args, domain, log)


def wait_exit(proc: RosProcess, timeout: float) -> int:
    proc.proc.wait(timeout)
    return proc.proc.returncode


def in_process_history(iterations: int, settings: dict, config: str = CONFIG) -> list[dict]:
    cfg = TrainConfig.from_sources(config, {**settings, "iterations": iterations})
    trainer = Trainer(cfg)
    for _ in range(iterations):
        trainer.train_iteration()
    return trainer.history


def assert_same_learning(over_ros: list[dict], in_process: list[dict]) -> None:
    assert [r["iteration"] for r in over_ros] == [r["iteration"] for r in in_process]
    for a, b in zip(over_ros, in_process, strict=True):
        a, b = metrics_without_timing(a), metrics_without_timing(b)
        for key in b:
            assert a[key] == pytest.approx(b[key], rel=1e-6, abs=1e-9), (key, a["iteration"])


@pytest.mark.parametrize("composed", [True, False], ids=["composed", "two_processes"])
def test_two_ppo_iterations_over_ros_equal_the_in_process_trainer(tmp_path, composed):
    domain = allocate_domain_id()
    arm = stack(domain, tmp_path, "pause", composed)
    try:
        lrn = learner(domain, tmp_path / "run", tmp_path / "learner.log", 2, SHORT)
        code = wait_exit(lrn, 240)
        assert code == 0, lrn.log() + logs(arm)
    finally:
        stop(arm)
    over_ros = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert all(r["dropped_episodes"] == 0 for r in over_ros)
    assert_same_learning(over_ros, in_process_history(2, SHORT))


def learn_over_composed(tmp_path: Path, config: str, settings: dict, arm_args: tuple[str, ...] = ()
                        ) -> tuple[list[dict], str]:
    """Two learner iterations against the composed arm, both started with ``config`` (the arm also with
    ``arm_args``): the learner's metrics rows (none with a dropped episode) and the arm's log."""
    domain = allocate_domain_id()
    arm = stack(domain, tmp_path, "pause", config=config, extra=arm_args)
    try:
        lrn = learner(domain, tmp_path / "run", tmp_path / "learner.log", 2, settings, config)
        assert wait_exit(lrn, 300) == 0, lrn.log() + logs(arm)
    finally:
        stop(arm)
    over_ros = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert all(r["dropped_episodes"] == 0 for r in over_ros)
    return over_ros, logs(arm)


def test_peg_over_the_composed_stack_equals_the_in_process_trainer(tmp_path):
    """The peg's held part (mass, TCP) is the same in the sim, the controller and the trainer: over
    ROS the learning equals the in-process run (with held_part: gear the TCP was 3 cm off)."""
    config = str(REPO / "config" / "peg.yaml")
    over_ros, arm_log = learn_over_composed(tmp_path, config, SHORT)
    assert "held part peg" in arm_log
    assert_same_learning(over_ros, in_process_history(2, SHORT, config))


def test_parameter_exploration_over_ros_equals_the_in_process_trainer(tmp_path):
    """make run's default task: learned S, D explored in parameter space, one published policy
    version per rollout, each rollout a deterministic controller. The policy carries its law: the arm's
    controller, given another force bound of its own (as an old hardware file would), warns that the
    parameter is ignored and runs the policy's 60 N, so the learning still equals the in-process run."""
    config = str(REPO / "config" / "gear_learn.yaml")
    settings = {**SHORT, "rollouts_per_iter": 4}
    over_ros, arm_log = learn_over_composed(tmp_path, config, settings,
                                            ("-p", "nf_controller:potential_force_bound:=30.0"))
    in_process = in_process_history(2, settings, config)
    # Iteration 1 runs the same parameter draws: equal. The controller's episode core sums some
    # terms in another order than the in-process rollout (returns differ by ~1e-13), and the
    # mirrored pairs' advantages (differences of nearly equal returns) carry that into the update;
    # after 0.5 s of gear contacts iteration 2's mean return differed by 6e-6 (measured, composed
    # and two-process alike). So iteration 2 is held to 1e-4.
    assert_same_learning(over_ros[:1], in_process[:1])
    assert over_ros[1]["return_mean"] == pytest.approx(in_process[1]["return_mean"], rel=1e-4)
    assert "policy version 1001 installed" in arm_log and "policy version 2000 installed" in arm_log
    assert ("parameter(s) potential_force_bound ignored: the law travels with the policy" in arm_log
            and "the policy's values win" in arm_log), arm_log
    assert "its law: force bound 60 N (0: off), k_rot 30 Nm/rad" in arm_log, arm_log


def test_a_latched_fault_makes_the_learner_wait_for_a_person_and_go_on_without_losing_the_iteration(tmp_path):
    """on_safe_hold: wait (the default, for hardware): a fault latched mid-run (a bad joint state
    from a third node) aborts the episode; the learner waits until clear_fault is called, then runs
    the episode again and finishes the iteration with nothing dropped."""
    domain = allocate_domain_id()
    probe = Probe(domain)
    status = probe.collect(ControllerStatus, "controller_status", RELIABLE)
    arm = stack(domain, tmp_path, "hold", composed=False)
    settings = {**SHORT, "rollouts_per_iter": 3}
    try:
        args = ["-m", "learner_node.node", "--ros-args", "--params-file", CONFIG,
                "-p", f"learner_node:out_dir:={tmp_path / 'run'}", "-p", "learner_node:iterations:=1",
                "-p", "episode_seconds:=0.5", "-p", "learner_node:rollouts_per_iter:=3",
                "-p", "learner_node:eval_episodes:=0"]
        lrn = RosProcess(args, domain, tmp_path / "learner.log")
        assert probe.spin_until(lambda: status and status[-1][1].mode == ControllerStatus.MODE_RUNNING, 120), \
            lrn.log() + logs(arm)
        bad = JointState(name=list(panda_spec.JOINT_NAMES), position=[float("nan")] * 7, velocity=[0.0] * 7)
        pub = probe.node.create_publisher(JointState, "joint_states", RELIABLE)
        assert probe.spin_until(lambda: (pub.publish(bad), status[-1][1].mode == ControllerStatus.MODE_SAFE_HOLD)[1],
                                20), logs(arm)
        assert probe.spin_until(lambda: "waiting for a person" in lrn.log(), 30), lrn.log()
        probe.spin_for(2.0)
        assert lrn.alive() and status[-1][1].mode == ControllerStatus.MODE_SAFE_HOLD  # it waits, it does not give up
        client = probe.node.create_client(Trigger, "/nf_controller/clear_fault")
        assert client.wait_for_service(timeout_sec=10.0)
        cleared = client.call_async(Trigger.Request())
        assert probe.spin_until(cleared.done, 10.0) and cleared.result().success
        assert wait_exit(lrn, 240) == 0, lrn.log() + logs(arm)
        assert "safe hold cleared: going on" in lrn.log()
    finally:
        stop(arm)
        probe.close()
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert [r["iteration"] for r in metrics] == [1] and metrics[0]["dropped_episodes"] == 0
    assert_same_learning(metrics, in_process_history(1, settings))


def test_learner_goal_parameter_reaches_the_published_policy_over_dds(tmp_path):
    """``-p learner_node:goal:=[...]`` as docs/hardware.md writes it (a goal measured on a real cell):
    the policy the learner publishes over DDS aims at it (x_ref) and its config.json keeps it; a goal
    of the wrong length stops the learner with exit code 2 and a message naming the setting. With
    ``init_checkpoint`` (``run_robot --from-checkpoint``) the published policy is the checkpoint's, its
    goal replaced; a missing checkpoint stops the learner the same way."""
    domain = allocate_domain_id()
    probe = Probe(domain)
    policies = probe.collect(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
    goal = [0.52, 0.03, 0.05]
    cfg = TrainConfig.from_sources(REPO / "config" / "gear_learn.yaml")
    sim = build_policy(cfg, np.array([0.5, 0.0, 0.07]))  # a "simulation" policy with other gains, as a checkpoint
    with torch.no_grad():
        sim.ln_s.add_(torch.tensor([0.5, 0.2, -0.4], dtype=torch.float64))
    sim.sync_gains()
    torch.save({"format": CHECKPOINT_FORMAT, "config": cfg.to_dict(), "iteration": 30, "policy": sim.state_dict(),
                "explorer": None}, tmp_path / "sim.pt")
    common = ["-m", "learner_node.node", "--ros-args", "--params-file", str(REPO / "config" / "gear_learn.yaml"),
              "-p", f"learner_node:out_dir:={tmp_path / 'run'}", "-p", "learner_node:server_timeout:=60.0"]
    try:
        with RosProcess([*common, "-p", "learner_node:goal:=[0.52,0.03,0.05]",
                         "-p", f"learner_node:init_checkpoint:={tmp_path / 'sim.pt'}"], domain,
                        tmp_path / "learner.log") as lrn:  # no arm: it publishes, then waits for the server
            assert probe.spin_until(lambda: bool(policies), 90), lrn.log()
            assert list(policies[0][1].x_ref) == pytest.approx(goal)
            assert json.loads((tmp_path / "run" / "config.json").read_text())["goal"] == pytest.approx(goal)
            published = PolicyParameters.from_msg(policies[0][1])
            np.testing.assert_allclose(published.stiffness, sim.to_params().stiffness, rtol=1e-12)
            # the flow's landscape moves with the goal: same normalised weights (flow_input_scale)
            arch, scale = sim.flow.arch, cfg.flow_input_scale
            normalised = rescale_flow_weights(arch, sim.to_params().weights, [0.5, 0.0, 0.07], scale, inverse=True)
            np.testing.assert_allclose(published.weights, rescale_flow_weights(arch, normalised, goal, scale),
                                       rtol=1e-12, atol=1e-12)
            assert policies[0][1].version == 0 and f"starting a new run from {tmp_path / 'sim.pt'}" in lrn.log()
    finally:
        probe.close()
    with RosProcess([*common, "-p", "learner_node:goal:=[0.5,0.0]"], domain, tmp_path / "bad.log") as bad:
        assert wait_exit(bad, 90) == 2, bad.log()
        assert "goal" in bad.log()
    with RosProcess([*common, "-p", f"learner_node:init_checkpoint:={tmp_path / 'none.pt'}"], domain,
                    tmp_path / "none.log") as bad:  # the run folder has no checkpoint of its own yet
        assert wait_exit(bad, 90) == 2, bad.log()
        assert f"not starting: init_checkpoint {tmp_path / 'none.pt'}: no such file" in bad.log()


def test_the_robot_runs_learner_takes_the_arm_settings_over_the_task_file(tmp_path):
    """The learner command run_robot builds (make run-franka), run for real: config/franka_learn.yaml, the
    second parameters file, sets the fixed-start step over gear_learn.yaml, whose other settings stay."""
    from nf_bringup.robot_run import _parse, robot_commands

    cfg = REPO / "config"
    args = _parse([f"--config={cfg / 'gear_learn.yaml'}", f"--hardware-config={cfg / 'franka.yaml'}",
                   f"--arm-settings={cfg / 'franka_learn.yaml'}", "--out", str(tmp_path / "run")])
    learner = robot_commands(args, tmp_path / "run", record=False)["learner"]
    domain = allocate_domain_id()
    with RosProcess([*learner[1:], "-p", "learner_node:server_timeout:=60.0"], domain, tmp_path / "learner.log") as lrn:
        config = tmp_path / "run" / "learner" / "config.json"
        probe = Probe(domain)
        try:
            assert probe.spin_until(config.exists, 90), lrn.log()
        finally:
            probe.close()
        written = json.loads(config.read_text())
    expected = TrainConfig.from_sources(cfg / "gear_learn.yaml")
    arm = yaml.safe_load((cfg / "franka_learn.yaml").read_text())["learner_node"]["ros__parameters"]
    assert arm["param_elite"] != "none" and arm["param_sigma_settle"] < 1.0 and arm["param_sigma_jump"] < 1.0
    for key in ("param_elite", "param_sigma_settle", "param_sigma_jump", "param_sigma_gains", "param_settle_rule"):
        assert written[key] == arm[key], key
    assert (expected.param_elite, expected.param_sigma_settle, expected.param_sigma_jump) == ("none", 0.8, 1.0)
    assert (expected.param_sigma_gains, expected.param_settle_rule) == (0.7, "batch")  # random starts' spread
    assert (arm["param_sigma_gains"], arm["param_settle_rule"]) == (0.5, "mean")  # the arm's, as measured
    for key in ("potential_force_bound", "rollouts_per_iter", "stiffness", "task"):
        assert written[key] == expected.to_dict()[key], key


def test_learner_killed_mid_iteration_holds_the_arm_and_resumes_without_losing_an_iteration(tmp_path):
    domain = allocate_domain_id()
    # The kill must land inside iteration 2, so an iteration has to outlast the probe's reaction on a
    # busy machine: 32 rollouts take several seconds (8 can finish before the probe reacts).
    settings = {**SHORT, "rollouts_per_iter": 32}
    probe = Probe(domain)
    status = probe.collect(ControllerStatus, "controller_status", RELIABLE)
    states = probe.collect(JointState, "joint_states", RELIABLE, convert=lambda m: np.array(m.velocity))
    arm = stack(domain, tmp_path, "hold")
    run = tmp_path / "run"
    try:
        first = learner(domain, run, tmp_path / "learner1.log", 3, settings)
        metrics = run / "metrics.json"
        assert probe.spin_until(lambda: metrics.exists() and len(json.loads(metrics.read_text())) >= 1, 240), \
            first.log()
        assert probe.spin_until(lambda: status and status[-1][1].mode != MODE_IDLE, 30)  # iteration 2 is running
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait(10)
        finished = len(json.loads(metrics.read_text()))
        assert finished == 1, f"the kill came after iteration 2 had ended ({finished} iterations): too late to test"
        # the running episode ends (0.5 s simulated) and the arm is held: velocities die out
        assert probe.spin_until(lambda: status[-1][1].mode == MODE_IDLE, 30), logs(arm)
        # lockstep: simulated time passes only as fast as this (possibly busy) machine runs the loop;
        # judged on a state that arrived after the hold began (none may have arrived yet)
        idle_at = len(states)

        def held_still() -> bool:
            return len(states) > idle_at and np.abs(states[-1][1]).max() < 1e-2

        assert probe.spin_until(held_still, 30), \
            f"{len(states)} joint states ({idle_at} before the hold), last {states[-1][1] if states else None}"
        assert status[-1][1].mode == MODE_IDLE and not status[-1][1].fault
        assert len(json.loads(metrics.read_text())) == 1  # iteration 2 never finished (nor will it)
        second = learner(domain, run, tmp_path / "learner2.log", 3, settings)
        assert wait_exit(second, 300) == 0, f"{second.log()}\n{logs(arm)}"
        assert "resuming from" in second.log() and "after iteration 1" in second.log()
    finally:
        stop(arm)
        probe.close()
    over_ros = json.loads(metrics.read_text())
    assert_same_learning(over_ros, in_process_history(3, settings))


def test_controller_unchanged_against_a_hardware_like_driver(tmp_path):
    """The driver compensates gravity itself and speaks only the two ros2_control topics; the
    controller (gravity compensation off, no reset service) holds, follows a policy, and runs and
    streams an episode."""
    domain = allocate_domain_id()
    probe = Probe(domain)
    arm = ArmModel(part=panda_spec.GEAR_PART)
    joints = JointMap()
    states = probe.collect(JointState, "joint_states", RELIABLE,
                           convert=lambda m: joints.map(m.name, m.position, m.velocity))
    chunks = probe.collect(RolloutChunk, "rollouts", RELIABLE)
    status = probe.collect(ControllerStatus, "controller_status", RELIABLE)
    # before the server starts: Fast DDS drops a service response to a reader the server has not yet
    # matched (100 ms), so the client's result reader must be known long before the goal is sent
    client = ActionClient(probe.node, RunEpisode, "run_episode")
    driver = RosProcess([str(REPO / "tests" / "peers" / "hw_driver.py")], domain, tmp_path / "driver.log")
    # Timing safety stays on, but loose: a shared, non-realtime machine can stall a process for
    # hundreds of ms, and a latched hold would stop the arm for
    # the rest of the test. Latching on stale states and on runs of misses is tested in
    # test_nodes_core.
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "gravity_compensation:=false",
                      "-p", "driver_effort:=command", "-p", "reset_service:=''", "-p", "idle_mode:=policy",
                      "-p", "state_timeout:=2.0",
                      "-p", "max_consecutive_misses:=500"],
                     domain, tmp_path / "controller.log")

    def report() -> str:
        last = status[-1][1] if status else None
        where = f"mode {last.mode}, fault {last.fault!r}" if last else "no status"
        modes = sorted({int(m.mode) for _, m in status})
        return (f"{len(states)} states received; controller {where}; modes seen {modes}; {len(chunks)} rollout "
                f"chunks\n{ctl.log()}\n{driver.log()}")

    try:
        assert probe.spin_until(lambda: len(states) > 100, 30), driver.log()
        x0 = arm.tcp_position(states[-1][1][0])
        goal = x0 + np.array([0.04, 0.0, -0.05])
        pub = probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
        pub.publish(policy_msg(goal, version=3))
        # the controller may still be loading its compiled kernels (cold cache on a fresh clone)
        assert probe.spin_until(lambda: status and status[-1][1].policy_version == 3, 60), report()

        def distance() -> float:
            return float(np.linalg.norm(arm.tcp_position(states[-1][1][0]) - goal))

        assert probe.spin_until(lambda: distance() < 0.005, 10), f"distance {distance():.4f} m; {report()}"
        assert client.wait_for_server(timeout_sec=10)
        sent = client.send_goal_async(RunEpisode.Goal(policy_version=3, seed=-1, noise_seed=1, duration=0.5))
        assert probe.spin_until(sent.done, 10) and sent.result().accepted
        done = sent.result().get_result_async()
        assert probe.spin_until(done.done, 60), report()
        result = done.result().result
        assert result.completed, f"{result.message}; {report()}"
        assert probe.spin_until(lambda: len(chunks) >= result.n_chunks, 5)
        assert [c.seq for _, c in chunks] == list(range(result.n_chunks)) and chunks[-1][1].final
        assert sum(len(c.t) for _, c in chunks) == 50
        assert np.all(np.isnan(np.concatenate([c.insertion_depth for _, c in chunks])))  # no ground truth
        assert driver.alive() and ctl.alive()
    finally:
        ctl.stop()
        driver.stop()
        probe.close()
