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
lockstep >= 10,000 steps/s (composed), an iteration over ROS <= 1.3x the one in process. The
composed driver loop is also timed with no ROS at all (its ceiling).
The settings are ``make run``'s (``config/gear_learn.yaml``) unless ``--config`` says otherwise.
Usage: python bench/bench_stack.py [--quick] [--config config/gear.yaml]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CONFIG = REPO / "config" / "gear_learn.yaml"  # make run's settings
TARGET_STEPS_PER_S = 10_000.0
TARGET_ROS_OVER_IN_PROCESS = 1.3


def ros_iteration(rollouts: int, seconds: float, domain: int, workdir: Path, composed: bool,
                  config: Path = CONFIG, monitor_period: float | None = None) -> dict:
    """One PPO iteration over ROS; returns the learner's metrics row. ``monitor_period`` overrides
    the composed sim's (s between its joint_states and applied-command messages; 0: every step)."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    params = ["--ros-args", "--params-file", str(config)]
    lockstep = ["-p", "nf_controller:idle_mode:=pause", "-p", "nf_controller:max_consecutive_misses:=0"]
    if monitor_period is not None:
        lockstep += ["-p", f"sim_bridge:monitor_period:={monitor_period}"]
    arm = [("nf_bringup.sim_stack", lockstep)] if composed else \
        [("sim_bridge_node.node", []), ("nf_controller_node.node", lockstep)]
    procs = [subprocess.Popen([sys.executable, "-m", mod, *params, *extra], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.STDOUT) for mod, extra in arm]
    try:
        out = workdir / f"run{domain}"
        learner = subprocess.run(
            [sys.executable, "-m", "learner_node.node", *params, "-p", f"learner_node:out_dir:={out}",
             "-p", "learner_node:iterations:=1", "-p", f"learner_node:rollouts_per_iter:={rollouts}",
             "-p", "learner_node:eval_episodes:=0", "-p", f"episode_seconds:={seconds}"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, timeout=900)
        if learner.returncode != 0:
            raise RuntimeError(f"learner exited with {learner.returncode}")
        return json.loads((out / "metrics.json").read_text())[-1]
    finally:
        for p in procs:  # stopped by PID
            p.send_signal(2)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def in_process_iteration(rollouts: int, seconds: float, config: Path = CONFIG) -> dict:
    """The same iteration in process (after one warm-up iteration compiles the kernels)."""
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer

    cfg = TrainConfig.from_sources(config, {"rollouts_per_iter": rollouts, "episode_seconds": seconds})
    trainer = Trainer(cfg)
    trainer.train_iteration()
    return trainer.train_iteration()


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
    import threading

    from nf_controller_node.episode import EpisodeRun, EpisodeSpec
    from nf_controller_node.host import EPISODE_END
    from sim_bridge_node.bridge import SimBridge
    from sim_bridge_node.composed import SimDriverLoop

    cfg, env, host = gear_host(config, "pause", {"rollouts_per_iter": rollouts, "episode_seconds": seconds})
    params = host.loop.policy
    driver = SimDriverLoop(SimBridge(env), host, realtime=False)
    stop = threading.Event()
    thread = threading.Thread(target=driver.run, args=(stop,), daemon=True)
    thread.start()
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
        stop.set()
        thread.join(10.0)
    return rates


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 repeats of 3 short episodes")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", type=Path, default=CONFIG, help="parameters file (default: make run's)")
    parser.add_argument("--monitor-period", type=float, default=None,
                        help="composed sim's monitor_period (s; 0: joint_states and commands every step; "
                             "default: the config's)")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "stack.json")
    args = parser.parse_args()
    rollouts, seconds, repeats = (3, 1.0, 2) if args.quick else (15, 5.0, args.repeats)
    steps = rollouts * round(seconds / 0.001)
    rows: dict[str, list[dict]] = {"composed": [], "separate": []}
    local = []  # the in-process iteration, interleaved with the ROS ones: this machine's speed drifts
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            for j, how in enumerate(rows):
                row = ros_iteration(rollouts, seconds, 150 + (os.getpid() + 2 * k + j) % 50, Path(tmp),
                                    composed=how == "composed", config=args.config,
                                    monitor_period=args.monitor_period)
                rows[how].append(row)
                print(f"over ROS, {how} {k + 1}/{repeats}: rollouts {row['rollout_seconds']:.2f} s "
                      f"({steps / row['rollout_seconds']:.0f} steps/s), update {row['update_seconds']:.2f} s",
                      flush=True)
            local.append(in_process_iteration(rollouts, seconds, args.config))
            print(f"in process {k + 1}/{repeats}: rollouts {local[-1]['rollout_seconds']:.2f} s "
                  f"({steps / local[-1]['rollout_seconds']:.0f} steps/s), wall {local[-1]['wall_seconds']:.2f} s",
                  flush=True)
    floor = []
    for k in range(repeats):  # the runtime's floor: a bare rclpy round trip between two processes
        env = dict(os.environ, ROS_DOMAIN_ID=str(150 + (os.getpid() + 7 + k) % 50),
                   ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        done = subprocess.run([sys.executable, str(HERE / "pingpong.py"), "--seconds", "5"], env=env,
                              capture_output=True, text=True, timeout=120)
        floor.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(f"rclpy ping-pong floor {k + 1}/{repeats}: {floor[-1]['round_trips_per_s']:.0f} round trips/s",
              flush=True)
    alone = loop_alone(rollouts, seconds, args.config)
    print(f"composed loop without ROS: median {statistics.median(alone):.0f} steps/s", flush=True)
    rates = [steps / r["rollout_seconds"] for r in rows["composed"]]
    ratios = [c["wall_seconds"] / i["wall_seconds"] for c, i in zip(rows["composed"], local, strict=True)]
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
        "lockstep_steps_per_s_loop_alone": {"median": statistics.median(alone), "min": min(alone),
                                            "max": max(alone), "all": alone,
                                            "what": "the composed driver loop with no ROS (one per episode)"},
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
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result["lockstep_steps_per_s"]), json.dumps(result["iteration_wall_s"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
