"""Bags from real runs: sim_bridge + nf_controller (lockstep) + the recorder as separate processes
over real DDS. Every recorded message reads back equal through two independent readers (mcap +
mcap_ros2, rosbags) and the one rclpy deserialises; counts match what the sim stepped; a replay
into a second recorder gives the same bytes; a recorded episode re-simulates to 1e-9; a recorder
killed with SIGKILL leaves its complete chunks readable and says what was lost."""

from __future__ import annotations

import json
import re
import signal
import time
from collections import defaultdict

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nf_bags import bagfile, reader, resim
from nf_bags.record import message_class
from nf_msgs.action import RunEpisode
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from nf_msgs.msg import RolloutChunk
from rclpy.action import ActionClient
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as Rosbag2Reader
from sensor_msgs.msg import JointState
from test_bags_latched import bag_domain_id

from nf_core import qos
from nf_core.topics import POLICY_PARAMETERS
from sim_bridge_node.env import InsertionEnv

from ros_testing import REPO, RosProcess
from test_nodes import RELIABLE, Probe, diag_values, policy_msg

pytestmark = pytest.mark.ros

SIM = ["-m", "sim_bridge_node.node", "--ros-args", "-p", "task:=gear", "-p", "mode:=lockstep"]
STACK_TOPICS = ["/joint_states", "/effort_controller/commands", "/clock", "/task_status", "/controller_status",
                "/rollouts", "/policy_parameters"]
EPISODE_SECONDS = 1.0
DT_NS = 1_000_000


def wait_recording(rec: RosProcess, probe: Probe, topics: list[str], timeout: float = 20.0) -> None:
    """Until the recorder's log says it subscribed to every one of ``topics``, then a moment to match."""
    def ready() -> bool:
        log = rec.log()
        return all(f"recording {t} (" in log for t in topics)

    assert probe.spin_until(ready, timeout), rec.log()
    probe.spin_for(1.0)


def last_sim_steps(diags: list) -> int:
    """Steps of the sim's latest diagnostics report."""
    values = [v for _, m in diags if (v := diag_values(m, "sim_bridge"))]
    return int(values[-1]["steps"]) if values else -1


@pytest.fixture(scope="module")
def episode_bag(tmp_path_factory):
    """One recorded lockstep run: the sim waits (the controller pauses between episodes) until the
    recorder listens, then one episode of EPISODE_SECONDS with a published policy."""
    tmp = tmp_path_factory.mktemp("episode_bag")
    bag = tmp / "bag"
    domain = bag_domain_id()
    probe = Probe(domain)
    chunks = probe.collect(RolloutChunk, "/rollouts", RELIABLE)
    diags = probe.collect(DiagnosticArray, "/diagnostics", RELIABLE)
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(bag)], domain, tmp / "recorder.log")
    sim = RosProcess(SIM, domain, tmp / "sim.log")
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "idle_mode:=pause",
                      "-p", "max_consecutive_misses:=0"], domain, tmp / "controller.log")
    out = {"bag": bag, "tmp": tmp}
    # early: Fast DDS drops a response to a reader the server has not matched within 100 ms
    client = ActionClient(probe.node, RunEpisode, "run_episode")
    try:
        policy = policy_msg(InsertionEnv("gear").goal_position, version=7)
        probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY).publish(policy)
        wait_recording(rec, probe, STACK_TOPICS, 30)
        assert client.wait_for_server(timeout_sec=20)
        sent = client.send_goal_async(RunEpisode.Goal(policy_version=7, seed=3, noise_seed=5,
                                                      duration=EPISODE_SECONDS))
        assert probe.spin_until(sent.done, 10) and sent.result().accepted, ctl.log()
        done = sent.result().get_result_async()
        assert probe.spin_until(done.done, 60), ctl.log()
        result = done.result().result
        assert result.completed, result.message
        assert probe.spin_until(lambda: len(chunks) >= result.n_chunks, 5)
        # the controller pauses: the sim stops stepping; two equal reports give its final step count
        previous, deadline = -1, time.monotonic() + 20
        while not (previous > 0 and last_sim_steps(diags) == previous) and time.monotonic() < deadline:
            previous = last_sim_steps(diags)
            probe.spin_for(1.1)
        assert previous > 0 and last_sim_steps(diags) == previous, sim.log()
        out.update(steps=last_sim_steps(diags), result=result, policy=policy, chunks=[c for _, c in chunks])
    finally:
        ctl.stop()
        sim.stop()
        probe.spin_for(0.5)
        out["recorder_exit"] = rec.stop()
        out["recorder_log"] = rec.log()
        probe.close()
    return out


def test_every_message_reads_back_equal_through_two_readers(episode_bag):
    bag = episode_bag["bag"]
    assert episode_bag["recorder_exit"] == 0, episode_bag["recorder_log"]
    health = bagfile.scan(bag)
    assert health.closed and not health.lost, health.report()
    assert dict(health.counts) == {k: v for k, v in health.metadata_counts.items() if v}

    # reader 1: mcap + mcap_ros2 (schemas from the bag); reference: rclpy on the recorded CDR bytes
    first = []
    for d in reader.read_messages(bag):
        ref = deserialize_message(d.raw.data, message_class(d.raw.type))
        plain = reader.as_plain(d.msg)
        assert reader.same(plain, reader.as_plain(ref)), (d.topic, plain)
        first.append((d.topic, d.log_time, plain))
    # reader 2: rosbags (its own MCAP parser, types from the bag's schemas)
    second = []
    with AnyReader([bag]) as r:
        for conn, t, raw in r.messages():
            second.append((conn.topic, t, reader.as_plain(r.deserialize(raw, conn.msgtype))))
    with Rosbag2Reader(bag) as r:
        assert r.message_count == len(first) == len(second)
    by_topic: dict[str, list] = defaultdict(list)
    other: dict[str, list] = defaultdict(list)
    for topic, t, m in first:
        by_topic[topic].append((t, m))
    for topic, t, m in second:
        other[topic].append((t, m))
    assert by_topic.keys() == other.keys()
    for topic, rows in by_topic.items():
        assert [t for t, _ in rows] == [t for t, _ in other[topic]], f"{topic}: log times differ"
        differ = sum(not reader.same(a, b) for (_, a), (_, b) in zip(rows, other[topic], strict=True))
        assert differ == 0, f"{topic}: {differ} messages differ between the readers"
        times = [t for t, _ in rows]
        assert times == sorted(times), f"{topic}: log times not monotonic"
    for topic in ("/joint_states", "/task_status", "/controller_status", "/clock"):
        times = [m["clock"] if topic == "/clock" else m["header"]["stamp"] for _, m in by_topic[topic]]
        stamps = [t["sec"] * 10**9 + t["nanosec"] for t in times]
        assert np.all(np.diff(stamps) >= 0), f"{topic}: stamps go back"

    # counts: what the publishers sent
    steps = episode_bag["steps"]
    assert steps >= EPISODE_SECONDS * 1000
    states = sorted({m["header"]["stamp"]["sec"] * 10**9 + m["header"]["stamp"]["nanosec"]
                     for _, m in by_topic["/joint_states"]})
    assert len(states) == steps + 2, "start state, reset state and one per step"
    assert np.all(np.diff(states) == DT_NS)
    labels = [m["layout"]["dim"][0]["label"] for _, m in by_topic["/effort_controller/commands"]]
    assert len(set(labels)) == steps, "one answer per stepped state"
    assert len(by_topic["/clock"]) == steps
    chunks = [m for _, m in by_topic["/rollouts"]]
    assert len(chunks) == episode_bag["result"].n_chunks and [c["seq"] for c in chunks] == list(range(len(chunks)))
    for sent, got in zip(episode_bag["chunks"], chunks, strict=True):  # what the probe received
        assert reader.same(reader.as_plain(sent), got)
    assert [reader.same(reader.as_plain(episode_bag["policy"]), m) for _, m in by_topic["/policy_parameters"]] == [True]
    print(f"bag: {len(first)} messages, {steps} lockstep steps, {len(chunks)} rollout chunks; "
          f"{sum(f.size for f in health.files) / 1e3:.0f} kB in {sum(f.chunks for f in health.files)} chunks")


def test_offline_reader_summary_episodes_and_plot(episode_bag, tmp_path):
    bag = episode_bag["bag"]
    summary = reader.summarize(bag)
    assert summary["resets"] == 2 and len(summary["episodes"]) == 1
    ep = summary["episodes"][0]
    result = episode_bag["result"]
    assert ep["complete"] and ep["episode_id"] == result.episode_id and ep["policy_version"] == 7
    assert ep["return"] == pytest.approx(result.episode_return, rel=1e-12)
    records = reader.episode_records(bag)
    assert len(records) == 1 and records[0].episode_return == pytest.approx(result.episode_return, rel=1e-12)
    png = reader.plot_run(bag, tmp_path / "run.png")
    assert png.stat().st_size > 10_000


def test_recorded_episode_resimulates_to_1e_9(episode_bag):
    bag = episode_bag["bag"]
    starts = resim.episode_starts(bag)
    assert len(starts) == 2  # the sim's start, and the episode's reset
    r = resim.resimulate(bag, starts[1])
    assert r.steps == episode_bag["steps"], r
    assert r.max_q_error <= 1e-9 and r.max_dq_error <= 1e-9 and r.max_effort_error <= 1e-9, r
    print(f"re-simulation: {r.steps} steps, max |q| error {r.max_q_error:.1e} rad, |dq| {r.max_dq_error:.1e} rad/s")


def timed_replay_offsets(bag, tmp_path, attempt: int) -> np.ndarray:
    """Replay /task_status at twice the recorded speed into a recorder: each message's arrival
    minus its due time (both from the first message), in s."""
    domain = bag_domain_id()
    timed = tmp_path / f"timed{attempt}"
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(timed), "--topics", "/task_status"], domain,
                     tmp_path / f"rec_timed{attempt}.log")
    try:
        play = RosProcess(["-m", "nf_bags.play", str(bag), "--rate", "2", "--wait", "10", "--topics", "/task_status"],
                          domain, tmp_path / f"play_timed{attempt}.log")
        assert play.proc.wait(60) == 0, play.log()
        time.sleep(0.3)
    finally:
        assert rec.stop() == 0, rec.log()
    t_orig = np.array([r.log_time for r in bagfile.iter_raw(bag, ["/task_status"])]) * 1e-9
    t_play = np.array([r.log_time for r in bagfile.iter_raw(timed)]) * 1e-9
    assert len(t_play) == len(t_orig)
    return (t_play - t_play[0]) - (t_orig - t_orig[0]) / 2.0


def test_replay_gives_a_second_recorder_the_same_bytes(episode_bag, tmp_path):
    bag = episode_bag["bag"]
    topics = ["/rollouts", "/policy_parameters", "/task_status", "/joint_states"]
    domain = bag_domain_id()
    copy = tmp_path / "copy"
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(copy), "--topics", *topics], domain, tmp_path / "rec.log")
    try:
        play = RosProcess(["-m", "nf_bags.play", str(bag), "--fast", "--wait", "10", "--topics", *topics],
                          domain, tmp_path / "play.log")
        assert play.proc.wait(60) == 0, play.log()
        time.sleep(0.5)
    finally:
        assert rec.stop() == 0, rec.log()
    original = defaultdict(list)
    for raw in bagfile.iter_raw(bag, topics):
        original[raw.topic].append(raw.data)
    replayed = defaultdict(list)
    for raw in bagfile.iter_raw(copy):
        replayed[raw.topic].append(raw.data)
    for topic in topics:
        assert replayed[topic] == original[topic], (topic, len(replayed[topic]), len(original[topic]), play.log())

    # recorded timing, at twice the speed: task_status arrives over half the recorded span. The
    # player reads ahead, so a late message is the machine's stall (a busy 2-core machine can keep
    # either process off the CPU for longer than the bound); a player off its schedule misses it in
    # every replay, so up to three replays are measured and one must hold the bound.
    worst = []
    for attempt in range(3):
        offsets = np.abs(timed_replay_offsets(bag, tmp_path, attempt))
        worst.append((round(float(offsets.max()), 3), int(offsets.argmax())))
        if offsets.max() < 0.05:
            break
    assert worst[-1][0] < 0.05, f"replay timing off in every replay (s, at message): {worst}"


def test_recorder_killed_with_sigkill_leaves_complete_chunks_readable(tmp_path):
    domain = bag_domain_id()
    bag = tmp_path / "bag"
    probe = Probe(domain)
    seen = probe.collect(JointState, "/joint_states", RELIABLE,
                         convert=lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(bag), "--chunk-seconds", "0.5", "--metadata-seconds", "0.2"],
                     domain, tmp_path / "recorder.log")
    sim = RosProcess(SIM, domain, tmp_path / "sim.log")
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "-p", "idle_mode:=policy"], domain,
                     tmp_path / "controller.log")
    try:
        probe.node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY).publish(
            policy_msg(np.array([0.45, 0.0, 0.35])))
        wait_recording(rec, probe, ["/joint_states", "/effort_controller/commands"], 30)
        # at least 2.3 s (3 closed chunks of 0.5 s) and 1,200 states: a busy machine steps the
        # lockstep pair slower (329 states in 2.3 s were seen with a training on the other core)
        start = len(seen)
        probe.spin_for(2.3)
        probe.spin_until(lambda: len(seen) - start >= 1200, 30)
        rec.proc.send_signal(signal.SIGKILL)
        killed_at = time.time_ns()
        rec.proc.wait(10)
        probe.spin_for(0.5)
    finally:
        ctl.stop()
        sim.stop()
        rec.stop()
        probe.close()
    health = bagfile.scan(bag)
    assert not health.closed and not health.files[0].complete
    assert health.files[0].chunks >= 3, health.report()
    # everything in the complete chunks reads back, with both readers
    stamps = [reader.stamp_ns(d.msg.header) for d in reader.read_messages(bag, ["/joint_states"])]
    assert len(stamps) > 500
    distinct = sorted(set(stamps))
    assert np.all(np.diff(distinct) == DT_NS), "no hole before the crash"
    # what was lost: at most the open chunk (0.5 s) plus the metadata period
    last_log = max(f.last_time for f in health.files)
    assert (killed_at - last_log) * 1e-9 < 0.5 + 0.2 + 0.3
    known, chunk = health.loss_window()
    lost = sum(health.lost.values())
    later = [s for _, s in seen if s > distinct[-1]]
    assert known < 0.5 + 0.3 and chunk == pytest.approx(0.5)
    assert health.lost.get("/joint_states", 0) <= len(later)
    report = health.report()
    assert "NOT CLOSED" in report and f"lost: at least {lost} messages" in report
    info = RosProcess(["-m", "nf_bags.info", str(bag), "--json"], domain, tmp_path / "info.log")
    assert info.proc.wait(30) == 1
    parsed = json.loads(info.log())
    assert parsed["lost"] == health.lost and not parsed["closed"]
    # rosbags wants a summary: `info --repair` writes the readable part whole into a copy, keeping the loss
    # on record; the crashed original stays as it is
    before = (bag / "bag_0.mcap").read_bytes()
    repair = RosProcess(["-m", "nf_bags.info", str(bag), "--repair"], domain, tmp_path / "repair.log")
    assert repair.proc.wait(30) == 0, repair.log()
    assert (bag / "bag_0.mcap").read_bytes() == before and "torn bytes" in repair.log()
    repaired = bagfile.scan(tmp_path / "bag.repaired")
    assert repaired.state == "repaired" and repaired.counts == health.counts and not repaired.lost
    assert f"the original lost {lost} messages" in repaired.report()
    with AnyReader([tmp_path / "bag.repaired"]) as r:
        n = sum(1 for c, _, raw in r.messages() if r.deserialize(raw, c.msgtype) is not None)
    assert n == sum(health.counts.values())
    print(f"killed: {sum(health.counts.values())} messages readable in {health.files[0].chunks} chunks, "
          f"{lost} counted by the metadata lost ({known:.2f} s before its last update, chunks {chunk:g} s); "
          f"{(killed_at - last_log) * 1e-9:.2f} s between the last readable message and the kill")


def test_offline_ppo_update_from_a_bag_equals_the_learner_iteration(tmp_path):
    """The learner node's first iteration over ROS, recorded; the same update run offline from
    the bag's rollouts gives the policy the learner published (and the same PPO statistics)."""
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer, episode_summary

    config = str(REPO / "config" / "gear.yaml")
    settings = {"episode_seconds": 0.5, "rollouts_per_iter": 2, "eval_episodes": 0}
    domain = bag_domain_id()
    bag = tmp_path / "bag"
    run = tmp_path / "run"
    probe = Probe(domain)
    rec = RosProcess(["-m", "nf_bags.record", "-o", str(bag), "--topics", "/rollouts", "/policy_parameters"],
                     domain, tmp_path / "recorder.log")
    sim = RosProcess(["-m", "sim_bridge_node.node", "--ros-args", "--params-file", config], domain,
                     tmp_path / "sim.log")
    ctl = RosProcess(["-m", "nf_controller_node.node", "--ros-args", "--params-file", config,
                      "-p", "nf_controller:idle_mode:=pause", "-p", "nf_controller:max_consecutive_misses:=0"],
                     domain, tmp_path / "controller.log")
    try:
        # the rollouts topic exists once the controller is up; the policy topic once the learner is
        wait_recording(rec, probe, ["/rollouts"], 30)
        # the recorder subscribes to the policy once it sees the learner's publisher: the learner waits
        # for it (and the controller) or a short run can end before the bag holds its policy
        args = ["-m", "learner_node.node", "--ros-args", "--params-file", config,
                "-p", f"learner_node:out_dir:={run}", "-p", "learner_node:iterations:=1",
                "-p", "learner_node:policy_subscribers:=2"]
        for key, value in settings.items():
            args += ["-p", f"learner_node:{key}:={value}" if key != "episode_seconds" else f"{key}:={value}"]
        learner = RosProcess(args, domain, tmp_path / "learner.log")
        learner.proc.wait(240)
        assert learner.proc.returncode == 0, learner.log()
        probe.spin_for(1.0)
    finally:
        ctl.stop()
        sim.stop()
        assert rec.stop() == 0, rec.log()
        probe.close()
    online = json.loads((run / "metrics.json").read_text())[0]
    assert online["dropped_episodes"] == 0
    published = [p for p in reader.policies(bag) if p.version == 1]
    assert len(published) == 1, [p.version for p in reader.policies(bag)]

    cfg = TrainConfig.from_sources(config, {**settings, "iterations": 1})
    trainer = Trainer(cfg)
    trainer.episode_seeds()  # the learner drew this iteration's seeds before its update
    success_depth = trainer.runner.env.scene.success_depth
    episodes = reader.episode_records(bag, success_depth=success_depth)
    assert len(episodes) == settings["rollouts_per_iter"]
    row = trainer.update(episodes, 0.0)
    offline = trainer.policy.to_params(version=1).fill_msg(PolicyParametersMsg())
    assert reader.same(reader.as_plain(offline), reader.as_plain(published[0])), "policy after the update differs"
    summary_keys = set(episode_summary(episodes))
    ppo_keys = [k for k in row if k not in summary_keys and not re.search(r"seconds|iteration", k)]
    assert ppo_keys
    for key in ppo_keys:
        assert row[key] == pytest.approx(online[key], rel=1e-9, abs=1e-12, nan_ok=True), key
    print(f"offline update from the bag = online iteration 1: policy weights equal, {ppo_keys} equal")
