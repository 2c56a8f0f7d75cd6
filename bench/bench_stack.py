"""Benchmark of the node stack over ROS 2: lockstep closed-loop rate of the arm and its controller
during the learner's episodes, composed in one process (``nf_sim_stack``, the default of
``make run``) and as two processes over topics, and the wall time of one PPO iteration over ROS
against the same iteration in process, all in the same run.

Starts the arm (composed, then separate) and the learner (own ROS_DOMAIN_ID, loopback only)
``--repeats`` times each, every learner doing one iteration, interleaved with the in-process
trainer's same iteration (this machine's speed drifts by up to 2x within minutes: each composed
iteration is also compared with the in-process one of its own round, ``pairwise_ratios``); then
the floor of the two-process runtime (``pingpong.py``: a bare rclpy round trip between two
processes, no work). Writes ``bench/results/stack.json``. Targets (issue 13):
lockstep >= 10,000 steps/s (composed), an iteration over ROS <= 1.3x the one in process. Every
round also runs the iteration's episodes through the composed driver loop with no ROS at all
(``loop_alone_iteration``, its ceiling), which splits the ratio (``rollout_split``): the driver path
(host, bridge, thread) over the in-process rollout, and ROS over the driver path.
The settings are ``make run``'s (``config/gear_learn.yaml``) unless ``--config`` says otherwise.
Usage: python bench/bench_stack.py [--quick] [--config config/gear.yaml] [--monitoring-ab]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import sources  # noqa: F401  (the package sources first on sys.path)

from nf_bringup.processes import RosProcess, allocate_domain_id, ros_env

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CONFIG = REPO / "config" / "gear_learn.yaml"  # make run's settings
TARGET_STEPS_PER_S = 10_000.0
TARGET_ROS_OVER_IN_PROCESS = 1.3


def ros_iteration(rollouts: int, seconds: float, domain: int, workdir: Path, composed: bool,
                  config: Path = CONFIG, monitor_period: float | None = None, monitor_always: bool = False) -> dict:
    """One PPO iteration over ROS; returns the learner's metrics row. ``monitor_period`` overrides
    the composed sim's (s between its joint_states and applied-command messages; 0: every step);
    ``monitor_always``: the composed sim publishes its monitoring topics with no subscriber too."""
    params = ["--ros-args", "--params-file", str(config)]
    lockstep = ["-p", "nf_controller:idle_mode:=pause", "-p", "nf_controller:max_consecutive_misses:=0"]
    if monitor_period is not None:
        lockstep += ["-p", f"sim_bridge:monitor_period:={monitor_period}"]
    if monitor_always:
        lockstep += ["-p", "sim_bridge:monitor_always:=true"]
    arm = [("nf_bringup.sim_stack", lockstep)] if composed else \
        [("sim_bridge_node.node", []), ("nf_controller_node.node", lockstep)]
    procs = [RosProcess(["-m", mod, *params, *extra], domain) for mod, extra in arm]
    try:
        out = workdir / f"run{domain}"
        learner = subprocess.run(
            [sys.executable, "-m", "learner_node.node", *params, "-p", f"learner_node:out_dir:={out}",
             "-p", "learner_node:iterations:=1", "-p", f"learner_node:rollouts_per_iter:={rollouts}",
             "-p", "learner_node:eval_episodes:=0", "-p", f"episode_seconds:={seconds}"],
            env=ros_env(domain), stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, timeout=900)
        if learner.returncode != 0:
            raise RuntimeError(f"learner exited with {learner.returncode}")
        return json.loads((out / "metrics.json").read_text())[-1]
    finally:
        for p in procs:
            p.stop(10.0)


def in_process_iteration(rollouts: int, seconds: float, config: Path = CONFIG) -> dict:
    """The same iteration in process: iteration 1 of a fresh trainer, the very episodes the learner
    runs in its iteration 1 (a first trainer's iteration compiles the kernels beforehand)."""
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer

    cfg = TrainConfig.from_sources(config, {"rollouts_per_iter": rollouts, "episode_seconds": seconds})
    Trainer(cfg).train_iteration()
    return Trainer(cfg).train_iteration()


def gear_host(config: Path, idle_mode: str, overrides: dict | None = None) -> tuple:
    """(TrainConfig, InsertionEnv, ControllerHost) of ``config``'s task, no ROS: the controller loop
    (``idle_mode``, no miss latch) running the untrained policy as version 1."""
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer
    from nf_controller_node.arm_model import ArmModel
    from nf_controller_node.control_loop import ControlLoop, LoopConfig
    from nf_controller_node.host import ControllerHost
    from sim_bridge_node.env import InsertionEnv

    cfg = TrainConfig.from_sources(config, overrides or {})
    env = InsertionEnv(cfg.task)
    params = Trainer(cfg).policy.to_params()
    params.version = 1
    loop = ControlLoop(ArmModel(part=env.scene.held_part), config=LoopConfig(idle_mode=idle_mode,
                                                                             max_consecutive_misses=0))
    loop.set_policy(params)
    return cfg, env, ControllerHost(loop)


def loop_alone(rollouts: int, seconds: float, config: Path = CONFIG) -> list[float]:
    """Steps/s of each episode of the composed driver loop with no ROS at all (``SimDriverLoop`` +
    ``ControllerHost`` on a thread, episodes started and drained by hand): the ceiling of the
    composed stack, what ROS's slow side and publishing take from it."""
    from nf_controller_node.host import EPISODE_END
    from nf_core.episode import EpisodeRun, EpisodeSpec
    from sim_bridge_node.bridge import SimBridge
    from sim_bridge_node.composed import SimDriverLoop

    cfg, env, host = gear_host(config, "pause", {"rollouts_per_iter": rollouts, "episode_seconds": seconds})
    params = host.loop.policy
    driver = SimDriverLoop(SimBridge(env), host, realtime=False)
    driver.start(logging.getLogger("bench_stack"))
    rates = []
    try:
        for i in range(rollouts):
            spec = EpisodeSpec(i, 1, seconds, cfg.decision_period, 0.001, None, i, params.x_ref.copy())
            run = EpisodeRun(spec)
            t0 = time.perf_counter()
            driver.begin_episode(i, run).result(timeout=60.0)
            while not any(e.kind == EPISODE_END for e in host.drain()):
                time.sleep(0.001)
            rates.append(run.steps / (time.perf_counter() - t0))
    finally:
        driver.stop(10.0)
    return rates


def loop_alone_iteration(rollouts: int, seconds: float, config: Path = CONFIG) -> dict:
    """The episodes of the trainer's iteration 1 (its starts and parameter draws, the work of the
    learner's iteration 1 and of ``in_process_iteration``) through the composed driver loop with no
    ROS: ``SimDriverLoop`` + ``ControllerHost`` on a thread, each rollout's parameters installed and
    its episode started by hand, the main thread woken by the host's ``notify``. What the driver
    path itself costs over the in-process rollout, and what ROS adds on top. Returns
    {"rollout_seconds", "steps"}."""
    import threading

    from learner_node.trainer import Trainer, policy_sigma
    from nf_controller_node.host import EPISODE_END
    from nf_core.episode import EpisodeRun, EpisodeSpec
    from sim_bridge_node.bridge import SimBridge
    from sim_bridge_node.composed import SimDriverLoop

    cfg, env, host = gear_host(config, "pause", {"rollouts_per_iter": rollouts, "episode_seconds": seconds})
    trainer = Trainer(cfg)
    plan = trainer.episode_plan()
    sigma = None if trainer.explorer is not None else policy_sigma(trainer.policy)
    driver = SimDriverLoop(SimBridge(env), host, realtime=False)
    woken = threading.Event()
    host.notify = woken.set
    driver.start(logging.getLogger("bench_stack"))
    steps = 0
    try:
        t0 = time.perf_counter()
        for i, (start, noise, params) in enumerate(plan):
            params = params if params is not None else trainer.policy.to_params()
            params.version = i + 2  # gear_host installed version 1
            host.call(lambda p=params: host.loop.set_policy(p)).result(timeout=60.0)
            spec = EpisodeSpec(i, params.version, seconds, cfg.decision_period, 0.001, sigma, noise,
                               params.x_ref.copy(), chunk_decisions=cfg.decisions_per_episode)
            run = EpisodeRun(spec)
            seed = trainer.runner.start_seed(start)
            driver.begin_episode(-1 if seed is None else seed, run).result(timeout=60.0)
            while not any(e.kind == EPISODE_END for e in host.drain()):
                woken.wait(1.0)
                woken.clear()
            steps += run.steps
        wall = time.perf_counter() - t0
    finally:
        driver.stop(10.0)
    return {"rollout_seconds": wall, "steps": steps}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 repeats of 3 short episodes")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", type=Path, default=CONFIG, help="parameters file (default: make run's)")
    parser.add_argument("--monitor-period", type=float, default=None,
                        help="composed sim's monitor_period (s; 0: joint_states and commands every step; "
                             "default: the config's)")
    parser.add_argument("--monitoring-ab", action="store_true",
                        help="each round also runs the composed iteration with the monitoring topics published "
                             "although nobody subscribes (sim_bridge:monitor_always), order alternated")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "stack.json")
    args = parser.parse_args()
    rollouts, seconds, repeats = (3, 1.0, 2) if args.quick else (15, 5.0, args.repeats)
    steps = rollouts * round(seconds / 0.001)
    rows: dict[str, list[dict]] = {"composed": [], "separate": []}
    local = []  # the in-process iteration, interleaved with the ROS ones: this machine's speed drifts
    alone: list[dict] = []  # the same episodes through the composed driver loop without ROS
    always: list[dict] = []  # --monitoring-ab: the composed iteration with sim_bridge:monitor_always
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            # the composed iteration and its in-process and loop-without-ROS counterparts back to back
            # (the pairwise ratios compare runs seconds apart); the slow two-process run last
            def monitored(k: int = k) -> dict:
                """The composed iteration with the monitoring published to nobody (sim_bridge:monitor_always)."""
                row = ros_iteration(rollouts, seconds, allocate_domain_id(), Path(tmp), composed=True,
                                    config=args.config, monitor_period=args.monitor_period, monitor_always=True)
                print(f"over ROS, composed, monitoring always published {k + 1}/{repeats}: rollouts "
                      f"{row['rollout_seconds']:.2f} s ({steps / row['rollout_seconds']:.0f} steps/s)", flush=True)
                return row

            if args.monitoring_ab and k % 2 == 1:  # before the default composed iteration, or after: alternately
                always.append(monitored())
            for how in rows:
                row = ros_iteration(rollouts, seconds, allocate_domain_id(), Path(tmp),
                                    composed=how == "composed", config=args.config,
                                    monitor_period=args.monitor_period)
                rows[how].append(row)
                print(f"over ROS, {how} {k + 1}/{repeats}: rollouts {row['rollout_seconds']:.2f} s "
                      f"({steps / row['rollout_seconds']:.0f} steps/s), update {row['update_seconds']:.2f} s",
                      flush=True)
                if how != "composed":
                    continue
                if args.monitoring_ab and k % 2 == 0:
                    always.append(monitored())
                local.append(in_process_iteration(rollouts, seconds, args.config))
                print(f"in process {k + 1}/{repeats}: rollouts {local[-1]['rollout_seconds']:.2f} s "
                      f"({steps / local[-1]['rollout_seconds']:.0f} steps/s), wall {local[-1]['wall_seconds']:.2f} s",
                      flush=True)
                alone.append(loop_alone_iteration(rollouts, seconds, args.config))
                print(f"composed loop without ROS {k + 1}/{repeats}: rollouts {alone[-1]['rollout_seconds']:.2f} s "
                      f"({alone[-1]['steps'] / alone[-1]['rollout_seconds']:.0f} steps/s)", flush=True)
    floor = []
    for k in range(repeats):  # the runtime's floor: a bare rclpy round trip between two processes
        done = subprocess.run([sys.executable, str(HERE / "pingpong.py"), "--seconds", "5"],
                              env=ros_env(allocate_domain_id()),
                              capture_output=True, text=True, timeout=120)
        floor.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(f"rclpy ping-pong floor {k + 1}/{repeats}: {floor[-1]['round_trips_per_s']:.0f} round trips/s",
              flush=True)
    rates = [steps / r["rollout_seconds"] for r in rows["composed"]]
    ratios = [c["wall_seconds"] / i["wall_seconds"] for c, i in zip(rows["composed"], local, strict=True)]
    rates_alone = [a["steps"] / a["rollout_seconds"] for a in alone]
    # where the time goes, per round (same episodes, rollout time): the driver path without ROS
    # over the in-process rollout, then ROS (nodes, DDS, the learner process, hand-overs) over it
    alone_over_local = [a["rollout_seconds"] / i["rollout_seconds"] for a, i in zip(alone, local, strict=True)]
    ros_over_alone = [c["rollout_seconds"] / a["rollout_seconds"] for c, a in zip(rows["composed"], alone, strict=True)]
    rates_separate = [steps / r["rollout_seconds"] for r in rows["separate"]]
    ros_wall = statistics.median(r["wall_seconds"] for r in rows["composed"])
    separate_wall = statistics.median(r["wall_seconds"] for r in rows["separate"])
    local_wall = statistics.median(r["wall_seconds"] for r in local)
    result = {
        "benchmark": "stack", "date": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": platform.machine(),
        "cpus": os.cpu_count(), "load_1min": os.getloadavg()[0],
        "config": str(args.config.resolve().relative_to(REPO)) if args.config.resolve().is_relative_to(REPO)
        else str(args.config), "monitor_period": args.monitor_period, "rollouts": rollouts,
        "episode_seconds": seconds, "repeats": repeats,
        "lockstep_steps_per_s": {"median": statistics.median(rates), "min": min(rates), "max": max(rates),
                                 "all": rates, "target": TARGET_STEPS_PER_S, "what": "composed (nf_sim_stack)"},
        "lockstep_steps_per_s_separate": {"median": statistics.median(rates_separate), "min": min(rates_separate),
                                          "max": max(rates_separate), "all": rates_separate,
                                          "what": "sim_bridge and nf_controller as two processes over topics"},
        "lockstep_steps_per_s_loop_alone": {"median": statistics.median(rates_alone), "min": min(rates_alone),
                                            "max": max(rates_alone), "all": rates_alone,
                                            "what": "the composed driver loop with no ROS, the iteration's own "
                                                    "episodes (one iteration per round)"},
        "rollout_split": {"loop_alone_over_in_process": alone_over_local,
                          "loop_alone_over_in_process_median": statistics.median(alone_over_local),
                          "ros_over_loop_alone": ros_over_alone,
                          "ros_over_loop_alone_median": statistics.median(ros_over_alone),
                          "what": "rollout time per round, same episodes: the driver path without ROS over the "
                                  "in-process rollout, then over ROS (composed) over the driver path without ROS"},
        "pingpong_floor": {"round_trips_per_s_median": statistics.median(f["round_trips_per_s"] for f in floor),
                           "median_us": statistics.median(f["median_us"] for f in floor), "all": floor,
                           "what": "bare rclpy round trip between two processes (bench/pingpong.py), no work"},
        "iteration_wall_s": {"over_ros_median": ros_wall, "in_process_median": local_wall,
                             "ros_over_in_process": ros_wall / local_wall, "target": TARGET_ROS_OVER_IN_PROCESS,
                             "pairwise_ratios": ratios, "pairwise_ratio_median": statistics.median(ratios),
                             "separate_median": separate_wall, "separate_over_in_process": separate_wall / local_wall,
                             "over_ros_all": [r["wall_seconds"] for r in rows["composed"]],
                             "separate_all": [r["wall_seconds"] for r in rows["separate"]],
                             "in_process_all": [r["wall_seconds"] for r in local]},
    }
    if always:
        always_ratios = [a["wall_seconds"] / c["wall_seconds"] for a, c in zip(always, rows["composed"], strict=True)]
        result["monitoring_ab"] = {
            "always_published_wall_s": [a["wall_seconds"] for a in always],
            "always_over_default": always_ratios, "always_over_default_median": statistics.median(always_ratios),
            "always_over_in_process": [a["wall_seconds"] / i["wall_seconds"]
                                       for a, i in zip(always, local, strict=True)],
            "what": "the composed iteration with joint_states, commands, clock and task_status published to nobody "
                    "(sim_bridge:monitor_always) over the default (published only while subscribed), same round"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result["lockstep_steps_per_s"]), json.dumps(result["iteration_wall_s"]),
          json.dumps(result["rollout_split"]), json.dumps(result.get("monitoring_ab", {})))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
