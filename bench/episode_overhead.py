"""What the composed host path costs over the in-process rollout, per episode, with no ROS at all.

The iteration ratio of ``bench_stack.py`` (over ROS vs in process) mixes three things: what our
host path does per step that the in-process rollout does not (joint-name mapping, plausibility
checks, stamps, latency accounting), what the ROS process adds (monitoring messages, the executor
thread, the learner and DDS threads on the second core), and this machine's drift (up to 2x within
minutes). This benchmark measures the first alone: in one process and one thread, it alternates an
in-process rollout episode (``RolloutRunner.run_episode``) with the same episode (same untrained
policy, same start seed) run by the composed driver loop (``SimDriverLoop`` + ``ControllerHost``,
lockstep, no publishing), and reports each pair's ratio of wall time and of thread CPU time per step.
Pairs close in time share the machine's speed, so their ratio is steadier than the two totals'.

Usage: python bench/episode_overhead.py [--pairs 12] [--seconds 5] [--quick]
Writes bench/results/episode_overhead.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import threading
import time
from pathlib import Path

from bench_stack import CONFIG, gear_host

HERE = Path(__file__).resolve().parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=12, help="episode pairs (in process, composed)")
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per episode")
    parser.add_argument("--config", type=Path, default=CONFIG)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "episode_overhead.json")
    parser.add_argument("--quick", action="store_true", help="4 pairs of 1 s episodes")
    args = parser.parse_args()
    if args.quick:
        args.pairs, args.seconds = 4, 1.0

    from learner_node.rollout import RolloutRunner
    from nf_controller_node.flow_eval import FlowEvaluator
    from nf_core.episode import EpisodeRun, EpisodeSpec
    from sim_bridge_node.bridge import SimBridge
    from sim_bridge_node.composed import SimDriverLoop

    cfg, env, host = gear_host(args.config, "pause", {"episode_seconds": args.seconds})
    params = host.loop.policy
    stop = threading.Event()

    def stop_after_episode() -> None:
        if host.loop.episode is None:
            stop.set()

    driver = SimDriverLoop(SimBridge(env), host, realtime=False, after_step=stop_after_episode)
    runner = RolloutRunner(cfg)
    evaluator = FlowEvaluator.from_params(params)

    def composed(seed: int) -> tuple[float, float, int]:
        spec = EpisodeSpec(seed, 1, args.seconds, cfg.decision_period, 0.001, None, seed, params.x_ref.copy())
        run = EpisodeRun(spec)
        driver.begin_episode(seed, run)  # runs at the loop's first service(), inside the timing
        stop.clear()
        t0, c0 = time.perf_counter(), time.thread_time()
        driver.run(stop)  # on this thread, until the episode ended
        wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
        host.drain()
        return wall, cpu, run.steps

    def in_process(seed: int) -> tuple[float, float, int]:
        t0, c0 = time.perf_counter(), time.thread_time()
        record = runner.run_episode(evaluator, None, seed, None)
        return time.perf_counter() - t0, time.thread_time() - c0, len(record.t) * cfg.steps_per_decision

    composed(10_000)  # compile and warm both paths once
    in_process(10_000)
    pairs = []
    for k in range(args.pairs):
        first, second = (in_process, composed) if k % 2 == 0 else (composed, in_process)  # alternate the order
        a, b = first(k), second(k)
        local, comp = (a, b) if first is in_process else (b, a)
        row = {"seed": k, "in_process_us_per_step": 1e6 * local[0] / local[2],
               "composed_us_per_step": 1e6 * comp[0] / comp[2],
               "wall_ratio": (comp[0] / comp[2]) / (local[0] / local[2]),
               "cpu_ratio": (comp[1] / comp[2]) / (local[1] / local[2])}
        pairs.append(row)
        print(f"pair {k + 1}/{args.pairs}: in process {row['in_process_us_per_step']:.1f} us/step, composed "
              f"{row['composed_us_per_step']:.1f} us/step, ratio {row['wall_ratio']:.3f} (CPU {row['cpu_ratio']:.3f})",
              flush=True)
    wall = [p["wall_ratio"] for p in pairs]
    cpu = [p["cpu_ratio"] for p in pairs]
    result = {
        "benchmark": "episode_overhead", "date": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": platform.machine(),
        "cpus": os.cpu_count(), "load_1min": os.getloadavg()[0], "episode_seconds": args.seconds,
        "what": "composed driver loop (no ROS) over the in-process rollout, per step, same episode, same thread",
        "wall_ratio": {"median": statistics.median(wall), "p25": statistics.quantiles(wall, n=4)[0],
                       "p75": statistics.quantiles(wall, n=4)[2], "all": wall},
        "cpu_ratio": {"median": statistics.median(cpu), "all": cpu},
        "pairs": pairs,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"composed loop over in-process rollout: median {result['wall_ratio']['median']:.3f} "
          f"(quartiles {result['wall_ratio']['p25']:.3f}-{result['wall_ratio']['p75']:.3f}) over {len(pairs)} pairs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
