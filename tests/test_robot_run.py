"""``run_robot`` (make run-franka): the commands it starts, its checks, its progress lines, and its main
end to end against franky-sim (one short iteration; the learning itself: docs/hardware.md's command)."""

from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nf_bringup.robot_run import ARM_STIFFNESS_FLOOR, FRANKY_GOAL, Progress, _parse, robot_commands
from nf_bringup.run_summary import write_summary

CONFIGS = [f"--config={Path(__file__).resolve().parents[1] / 'config' / 'gear_learn.yaml'}",
           f"--hardware-config={Path(__file__).resolve().parents[1] / 'config' / 'franka.yaml'}",
           f"--arm-settings={Path(__file__).resolve().parents[1] / 'config' / 'franka_learn.yaml'}"]


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


def test_a_task_file_gives_the_cell_and_its_goal_to_both_nodes(tmp_path, capsys):
    task = Path(__file__).resolve().parents[1] / "config" / "tasks" / "examples" / "gear_side_fixture.yaml"
    args = _parse(["--task", str(task), "--out", str(tmp_path)])
    cmds = robot_commands(args, tmp_path, record=False)
    goal = "[0.42,0.18,0.09999999999999999]"  # the seated pose: 2 cm of pin below the mouth at z 0.12
    assert _value(cmds["arm"], "franka_driver:goal") == _value(cmds["learner"], "learner_node:goal") == goal
    assert _value(cmds["arm"], "franka_driver:fixture_position") == "[0.42,0.18,0.12]"
    assert _value(cmds["arm"], "franka_driver:start_position") == "[0.42,0.18,0.27]"
    assert _value(cmds["arm"], "franka_driver:success_depth") == "0.016"
    assert _value(cmds["arm"], "held_part") == "gear" and _value(cmds["learner"], "task") == str(task)
    with pytest.raises(SystemExit):  # a peg task is not a Franka gear cell
        _parse(["--task", "peg", "--out", str(tmp_path)])
    assert "the Franka cell holds a gear task" in capsys.readouterr().err


def test_the_arms_controller_gets_no_law_of_its_own(tmp_path):
    """The force bound and gains travel with the policy (its law): the Franka stack's command sets none."""
    cmds = robot_commands(_parse([*CONFIGS, "--out", str(tmp_path)]), tmp_path, record=False)
    for name in ("potential_force_bound", "k_rot", "d_rot", "joint_damping"):
        assert not any(name in a for a in cmds["arm"]), cmds["arm"]


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


def test_from_checkpoint_reaches_the_learner_and_the_summary_says_where_the_prior_came_from(tmp_path, capsys,
                                                                                          monkeypatch):
    """``--from-checkpoint`` (issue 30): the learner's init_checkpoint, absolute, beside the cell's goal;
    a missing file stops the command before anything starts, unless the run folder has its own
    checkpoint (the learner resumes that one); summary.md names the checkpoint the prior came from."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "checkpoint.pt").write_bytes(b"")
    args = _parse([*CONFIGS, "--out", "run", "--from-checkpoint", "sim/checkpoint.pt", "--iterations", "2"])
    learner = robot_commands(args, args.out, record=False)["learner"]
    assert _value(learner, "learner_node:init_checkpoint") == str(tmp_path / "sim" / "checkpoint.pt")
    assert _value(learner, "learner_node:goal") == "[" + ",".join(repr(float(v)) for v in FRANKY_GOAL) + "]"
    assert _value(learner, "learner_node:iterations") == "2"
    plain = robot_commands(_parse([*CONFIGS, "--out", "x"]), tmp_path, record=False)["learner"]
    assert not any("init_checkpoint" in a for a in plain)
    with pytest.raises(SystemExit):
        _parse([*CONFIGS, "--out", "run", "--from-checkpoint", "nowhere.pt"])
    assert "--from-checkpoint nowhere.pt: no such file" in capsys.readouterr().err
    (tmp_path / "run" / "learner").mkdir(parents=True)
    (tmp_path / "run" / "learner" / "checkpoint.pt").write_bytes(b"")  # its own: resumed, the other not read
    assert _parse([*CONFIGS, "--out", "run", "--from-checkpoint", "nowhere.pt"]).from_checkpoint.name == "nowhere.pt"
    (tmp_path / "run" / "learner" / "checkpoint.pt").unlink()
    started = {"checkpoint": str(tmp_path / "sim" / "checkpoint.pt"), "iteration": 30, "task": "gear",
               "x_ref": [0.5, 0.0, 0.07]}
    for name, iteration in (("evaluation_prior.json", 0), ("evaluation.json", 2)):
        (tmp_path / "run" / "learner" / name).write_text(json.dumps(
            {"episodes": 10, "iteration": iteration, "success_rate": 0.5, "final_distance_mean": 0.01,
             "return_mean": -1.0, "started_from": started}))
    (tmp_path / "run" / "learner" / "config.json").write_text(json.dumps({"task": "gear", "goal": list(FRANKY_GOAL)}))
    summary = write_summary(tmp_path / "run", tmp_path / "c.yaml", 60.0, 0, how="franky-sim").read_text()
    assert (f"Started from `{started['checkpoint']}` (after iteration 30 of a gear run, goal [0.5, 0.0, 0.07]): the "
            "prior is that policy, unchanged but for this run's goal [0.5, 0.0, 0.05]") in summary
    assert f"| the prior, started from {started['checkpoint']} (before iteration 1) | 10 |" in summary


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_runner_stops_cleanly_on_any_stop_signal_even_started_with_sigint_ignored(sig):
    """make run / make run-franka started in the background by a shell without job control get SIGINT
    ignored, and SIGTERM used to end the runner alone, leaving its children running: stop_on_signals makes
    each of them a KeyboardInterrupt, the path that stops the children and writes the summary."""
    code = ("import time\nfrom nf_bringup.processes import stop_on_signals\nstop_on_signals()\n"
            "try:\n    print('ready', flush=True)\n    time.sleep(60)\nexcept KeyboardInterrupt as exc:\n"
            "    print('stopped', exc, flush=True)\n")  # 'ready' inside the try: the signal may come at once
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert out.strip() == f"stopped {sig.name}" and proc.returncode == 0


def test_the_arm_settings_reach_the_learner_after_the_task_file_from_scratch_only(tmp_path, capsys):
    """config/franka_learn.yaml (the fixed-start step) is the learner's second parameters file, so it wins
    over the task file; --from-checkpoint (fine-tuning, measured without it) and --arm-settings none leave
    it out; a file that would set other nodes' parameters is refused before anything starts."""
    arm_settings = Path(__file__).resolve().parents[1] / "config" / "franka_learn.yaml"
    args = _parse([*CONFIGS, "--out", str(tmp_path)])
    learner = robot_commands(args, tmp_path, record=False)["learner"]
    files = [learner[i + 1] for i, a in enumerate(learner) if a == "--params-file"]
    assert files == [CONFIGS[0].split("=", 1)[1], str(arm_settings)]
    none = robot_commands(_parse([*CONFIGS, "--arm-settings", "none", "--out", "x"]), tmp_path, record=False)
    assert none["learner"].count("--params-file") == 1
    (tmp_path / "sim.pt").write_bytes(b"")
    tuned = _parse([*CONFIGS, "--out", "x", "--from-checkpoint", str(tmp_path / "sim.pt")])
    assert robot_commands(tuned, tmp_path, record=False)["learner"].count("--params-file") == 1
    other = tmp_path / "other.yaml"
    other.write_text("/**:\n  ros__parameters:\n    potential_force_bound: 0.0\n")
    with pytest.raises(SystemExit):
        _parse([*CONFIGS, f"--arm-settings={other}", "--out", "x"])
    assert "need one section, learner_node" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _parse([*CONFIGS, f"--arm-settings={tmp_path / 'missing.yaml'}", "--out", "x"])
    typo = tmp_path / "typo.yaml"
    typo.write_text("learner_node:\n  ros__parameters:\n    param_elite: sucseeded\n")
    with pytest.raises(SystemExit):
        _parse([*CONFIGS, f"--arm-settings={typo}", "--out", "x"])
    assert "param_elite must be one of" in capsys.readouterr().err


def test_the_arms_stiffness_floor_reaches_a_learner_that_starts_from_a_checkpoint(tmp_path, capsys):
    """A frictionless simulation can learn a spring the arm's friction stalls: from a checkpoint the learner
    gets ARM_STIFFNESS_FLOOR, from scratch none (the arm's rollouts carry its friction); either can be
    set, and a negative one is refused before anything starts."""
    cmds = robot_commands(_parse([*CONFIGS, "--out", str(tmp_path)]), tmp_path, record=False)
    assert _value(cmds["learner"], "learner_node:stiffness_floor") == "0.0"
    ckpt = tmp_path / "sim.pt"
    ckpt.write_bytes(b"")
    for extra, floor in (([], repr(ARM_STIFFNESS_FLOOR)), (["--stiffness-floor=0"], "0.0")):
        args = _parse([*CONFIGS, "--out", str(tmp_path / "ft"), "--from-checkpoint", str(ckpt), *extra])
        learner = robot_commands(args, tmp_path / "ft", record=False)["learner"]
        assert _value(learner, "learner_node:stiffness_floor") == floor
    args = _parse([*CONFIGS, "--out", str(tmp_path), "--stiffness-floor=300"])
    assert _value(robot_commands(args, tmp_path, record=False)["learner"], "learner_node:stiffness_floor") == "300.0"
    with pytest.raises(SystemExit):
        _parse([*CONFIGS, "--out", str(tmp_path), "--stiffness-floor=-5"])
    assert "--stiffness-floor must be >= 0" in capsys.readouterr().err


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(900)  # reset motions on a simulator that runs below real time on a loaded machine
def test_run_robot_end_to_end_on_franky_sim(tmp_path):
    """``make run-franka``'s own main: franky-sim with the gear cell, the Franka stack, the recorder and the
    learner with gear_learn.yaml + franka_learn.yaml, for one short iteration (3 rollouts of 1 s, one
    evaluation episode): it exits 0 and leaves the run folder make run leaves, and the
    arm ran the law the learner's policy carried (the task file's 60 N bound)."""
    from mcap.reader import make_reader

    from ros_testing import RosProcess, allocate_domain_id

    domain = allocate_domain_id()
    short = ["learner_node:rollouts_per_iter:=3", "learner_node:eval_episodes:=1", "learner_node:episode_seconds:=1.0",
             "learner_node:evaluate_prior:=false"]
    # a loaded machine can garble franky-sim's very first motion ("Unexpected reply to a Move command"), after
    # which the stack does not recover yet (status stops, the learner gives up); then the whole run starts once more
    for attempt in ("run", "again"):
        out = tmp_path / attempt
        args = ["-m", "nf_bringup.robot_run", "--iterations", "1", "--out", str(out), "--domain-id", str(domain),
                *[a for kv in short for a in ("--learner-arg=-p", f"--learner-arg={kv}")]]
        run = RosProcess(args, domain, tmp_path / f"run_robot_{attempt}.log")
        try:
            code = run.proc.wait(840)
        finally:
            run.stop()
        if code != 0 and attempt == "run" and "Unexpected reply to a Move command" in run.log():
            print("franky-sim garbled the first motion; the run starts once more")
            continue
        assert code == 0, run.log()
        break
    log = run.log()
    assert "[run] franky-sim up on 127.0.0.1 (FR3, gear cell)" in log and "[run] done in" in log, log
    history = json.loads((out / "learner" / "metrics.json").read_text())
    assert [r["iteration"] for r in history] == [1] and history[0]["dropped_episodes"] < 2, history
    summary = (out / "summary.md").read_text()
    assert "evaluation" in summary.lower() and (out / "learning_curves.png").exists(), summary
    arm_log = (out / "logs" / "arm.log").read_text()
    assert "its law: force bound 60 N" in arm_log, arm_log
    bags = list((out / "bag").glob("*.mcap"))
    assert bags, list((out / "bag").iterdir())
    with open(bags[0], "rb") as f:  # the mcap library's own reader, not the project's
        topics = {channel.topic for _, channel, _ in make_reader(f).iter_messages()}
    assert {"/policy_parameters", "/joint_states", "/rollouts"} <= topics, topics
    # the bag re-simulates in closed loop (nf_bags.resim_policy): each episode's policy with its recorded noise,
    # from its recorded start, in our simulated cell (franky's: the shaft's top 2 cm lower than gear.yaml's)
    # with the friction identified from the bag, follows the FR3's joints
    from nf_bags.friction import identify_bag
    from nf_bags.reader import joint_trajectory, rollout_chunks, stamp_ns
    from nf_bags.resim_policy import START_GAP, START_MATCH, resimulate_bag

    from nf_controller_node.arm_model import ArmModel
    from nf_core.task_spec import held_part_inertia

    text = (Path(__file__).resolve().parents[1] / "config" / "tasks" / "gear.yaml").read_text()
    assert "position: [0.5, 0.0, 0.09]" in text
    cell = tmp_path / "franky_cell.yaml"
    cell.write_text(text.replace("position: [0.5, 0.0, 0.09]", "position: [0.5, 0.0, 0.07]"))
    friction = identify_bag(out / "bag").sim_parameters()
    skipped: list[str] = []
    results = resimulate_bag(out / "bag", task=str(cell), friction=(friction["joint_friction"],
                                                                     friction["joint_viscous"]), skipped=skipped)
    # an episode is left out only where the driver's 100 Hz joint states stalled (a loaded machine)
    assert results and all("no joint state recorded" in why or "do not cover" in why for why in skipped), skipped
    # alone on the machine every episode stays within 0.02 rad and ends within 3 mm (docs/measurements.md);
    # under a test suite's load the driver misses cycles the bag does not record (the robot holds the last
    # command), and errors up to 0.08 rad and 22 mm were seen: bounds that still catch a wrong start, policy
    # or stamp (0.3-0.8 rad)
    assert all(r.max_q_error < 0.15 and r.rms_q_error < 0.05 and r.final_tcp_error < 0.03 for r in results), results
    # every chunk is stamped as its first sample: where joint states surround that stamp, they put the TCP there
    traj, arm = joint_trajectory(out / "bag"), ArmModel(part=held_part_inertia("gear"))
    checked = 0
    for chunks in rollout_chunks(out / "bag").values():
        first = min(chunks, key=lambda c: c.seq)
        t = stamp_ns(first.header)
        i = int(np.searchsorted(traj.stamp_ns, t))
        if not 0 < i < len(traj.stamp_ns) or traj.stamp_ns[i] - traj.stamp_ns[i - 1] > START_GAP:
            continue
        q = [np.interp(t, traj.stamp_ns, traj.q[:, k]) for k in range(7)]
        assert np.linalg.norm(arm.tcp_position(np.array(q)) - np.array(first.x[:3])) < START_MATCH
        checked += 1
    assert checked >= 1
    print("closed-loop re-simulation:", [(round(r.max_q_error, 4), round(1e3 * r.final_tcp_error, 1)) for r in results],
          "left out:", skipped)
