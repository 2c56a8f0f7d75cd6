"""Run every benchmark in sequence (never in parallel: the machine has 2 cores) and collect JSON.

Each benchmark writes bench/results/<name>.json; this prints a one-line summary per target.
Usage: python bench/run_all.py [--quick]   (the realtime benchmark alone takes about 27 minutes: 10
composed and 10 over topics, plus its shorter phases; the Franka driver's 10; --quick: about 4 minutes
and 30 s; the many-arms scaling, bench_arms.py, about 15 minutes more, --quick 2)
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"


def _run(name: str, cmd: list[str]) -> dict | None:
    out = RESULTS / f"{name}.json"
    print(f"== {name}: {' '.join(cmd)}", flush=True)
    t0 = time.monotonic()
    done = subprocess.run(cmd, cwd=HERE.parent)
    print(f"== {name}: exit {done.returncode} after {time.monotonic() - t0:.0f} s", flush=True)
    return json.loads(out.read_text()) if done.returncode == 0 and out.exists() else None


def _bags_line(bags: dict) -> str:
    return (f"   recording: {bags['messages_per_s']:.0f} msg/s, {bags['payload_mb_per_s']:.2f} MB/s, recorder CPU "
            f"{100 * bags['recorder_cpu_fraction']:.0f} % of a core, no drops: {bags['no_drops']}")


def _stack_line(stack: dict) -> str:
    r, w, sep = stack["lockstep_steps_per_s"], stack["iteration_wall_s"], stack["lockstep_steps_per_s_separate"]
    return (f"   lockstep, composed: median {r['median']:.0f} steps/s (target >= {r['target']:.0f}); two processes "
            f"{sep['median']:.0f} steps/s (bare rclpy ping-pong floor "
            f"{stack['pingpong_floor']['round_trips_per_s_median']:.0f}/s); PPO iteration composed "
            f"{w['over_ros_median']:.1f} s, two processes {w['separate_median']:.1f} s, in process "
            f"{w['in_process_median']:.1f} s ({w['ros_over_in_process']:.1f}x / {w['separate_over_in_process']:.1f}x; "
            f"target <= {w.get('target', 1.3):.1f}x), {stack.get('config', 'config/gear.yaml')}")


def _realtime_line(realtime: dict) -> str:
    k, t = realtime["composed"], realtime["composed_targets"]
    line = (f"   realtime 1 kHz composed ({realtime['seconds']['composed']:.0f} s): state->torque median "
            f"{k['p50_us']:.0f} us, p99 {k['p99_us']:.0f} us (target <= {t['p99_us_max']:.0f}), p99.9 "
            f"{k['p999_us']:.0f} us, late ticks {100 * k['late_fraction']:.3f} % (<= "
            f"{100 * t['late_fraction_max']:g} %), longest run of late ticks {k['longest_late_run']} "
            f"(<= {t['longest_late_run_max']})")
    asleep, floor = realtime.get("composed_sleep"), realtime.get("wake_floor")
    if asleep:
        line += (f"\n   the same, periods waited asleep ({realtime['seconds']['composed_sleep']:.0f} s): p99 "
                 f"{asleep['p99_us']:.0f} us, late ticks {100 * asleep['late_fraction']:.3f} %, longest run "
                 f"{asleep['longest_late_run']}")
    cold = realtime.get("composed_cold")
    if cold:
        line += (f"\n   the same without the cache warm-up ({realtime['seconds']['composed_cold']:.0f} s): median "
                 f"{cold['p50_us']:.0f} us, p99 {cold['p99_us']:.0f} us, late ticks "
                 f"{100 * cold['late_fraction']:.3f} %")
    normal = realtime.get("composed_normal")
    if normal:
        line += (f"\n   the same with the driver thread at normal scheduling instead of "
                 f"{k.get('loop_scheduling', '?')} ({realtime['seconds']['composed_normal']:.0f} s): p99 "
                 f"{normal['p99_us']:.0f} us, late ticks {100 * normal['late_fraction']:.3f} %, longest run "
                 f"{normal['longest_late_run']}")
    if floor:
        line += (f"\n   this machine's wake-up floor (a loop with no work): more than 1 ms late "
                 f"{100 * floor['asleep']['late_1ms_fraction']:.3f} % asleep, "
                 f"{100 * floor['deadline_wait']['late_1ms_fraction']:.3f} % with DeadlineWait")
    if realtime.get("controller") is None:
        return line
    c, e = realtime["controller"], realtime["baseline_echo"]
    return line + "\n" + (
            f"   realtime 1 kHz over topics ({realtime['seconds']['controller']:.0f} s): latency median "
            f"{c['p50_us']:.0f} us, "
            f"p99 {c['p99_us']:.0f} us (target <= {realtime['targets']['p99_us_max']:.0f}), misses "
            f"{100 * c['miss_fraction']:.2f} %, longest run {c['longest_miss_run']} (target < "
            f"{realtime['targets']['longest_miss_run_below']}); echo baseline p99 {e['p99_us']:.0f} us")


def _franka_line(franka: dict) -> str:
    lat, t = franka["latency"], franka["targets"]
    return (f"   Franka driver vs franky-sim ({franka['seconds']:.0f} s, {franka['arm']}): readOnce->writeOnce "
            f"median {lat['p50_us']:.0f} us, p99 {lat['p99_us']:.0f} us (target <= {t['p99_us_max']:.0f}), p99.9 "
            f"{lat['p999_us']:.0f} us (<= {t['p999_us_max']:.0f}), max {lat['max_us']:.0f} us; loop period p99 "
            f"{franka['period']['p99_us']:.0f} us; longest run of late ticks {franka['longest_late_run']} "
            f"(< {t['late_run_below']}); libfranka exceptions {franka['exceptions']}")


def _trace_line(trace: dict) -> str:
    h, m = trace["handover"], trace["handover"]["median_ms"]
    ros, alone = trace["in_episode"]["over_ros"], trace["in_episode"]["without_ros"]
    top = ", ".join(f"{name.split('.')[-1]} {ms:.0f}" for name, ms in
                    list(trace["in_episode"]["stall_excess_ms_by_overlap_median"].items())[:3])
    return (f"   between two episodes over ROS: median {m['handover']:.1f} ms ({100 * h['share_of_rollouts']:.1f} % of "
            f"the rollout time; spin lock {m['spin_lock_wait']:.2f} ms); inside episodes, steps stalled beyond the "
            f"median: {statistics.median(r['stall_excess_ms'] for r in ros):.0f} ms over ROS vs "
            f"{statistics.median(r['stall_excess_ms'] for r in alone):.0f} ms without ROS per iteration "
            f"(overlapping: {top} ms)")


def _arms_line(arms: dict) -> str:
    rt, ls = arms["realtime"], arms["lockstep"]
    parts = [f"N={n}: iteration {v['iteration_wall_s_median']:.1f} s ({v['iteration_wall_ratio_to_1']:.2f}x), "
             f"{v['arm_cpu_cores_median']:.2f} cores per arm" for n, v in rt.items()]
    steps = ", ".join(f"N={n} {v['steps_per_s_median']:.0f} ({v['steps_per_s_ratio_to_1']:.2f}x)"
                      for n, v in ls.items())
    return (f"   many arms, realtime ({arms['rollouts']} rollouts of {arms['episode_seconds']:g} s): {'; '.join(parts)}"
            f"\n   many arms, lockstep steps/s summed: {steps}\n   {arms['where_cores_run_out']}")


# (name, script, one-line summary of its JSON): run in this order after the ROS-free benchmarks
_ROS_BENCHMARKS = (("bags", "bench_bags.py", _bags_line), ("stack", "bench_stack.py", _stack_line),
                   ("ros_iteration_trace", "trace_ros_iteration.py", _trace_line),
                   ("realtime", "bench_realtime.py", _realtime_line), ("franka", "bench_franka.py", _franka_line),
                   ("arms", "bench_arms.py", _arms_line))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer calls, for a smoke run")
    args = parser.parse_args()
    RESULTS.mkdir(exist_ok=True)
    calls = ["--calls", "20000", "--autograd-calls", "300"] if args.quick else []
    failed = []
    ctrl = _run("controller_step", [sys.executable, str(HERE / "bench_controller.py"), *calls,
                                    "--out", str(RESULTS / "controller_step.json")])
    if ctrl is None:
        failed.append("controller_step")
    else:
        for r in ctrl["results"]:
            a, c, s = r["arch"], r["compiled_step"], r["autograd_step"]
            p, b = r["compiled_step_posture_spring"], r["compiled_step_force_bound"]
            print(f"   n_flow={a['n_flow']} n_h={a['n_hidden']}: compiled median {c['median_us']:.1f} us, "
                  f"p99 {c['p99_us']:.1f} us (posture spring on, a reset's step: {p['median_us']:.1f} us, "
                  f"p99 {p['p99_us']:.1f} us; force bound on: {b['median_us']:.1f} us, p99 {b['p99_us']:.1f} us); "
                  f"autograd median {s['median_us']:.0f} us; "
                  f"speedup {r['speedup_median']:.0f}x")
    sim_script = HERE / "bench_sim.py"
    if sim_script.exists():
        if _run("sim", [sys.executable, str(sim_script), *(["--quick"] if args.quick else [])]) is None:
            failed.append("sim")
    learner_script = HERE / "bench_learner.py"
    if learner_script.exists():
        learner = _run("learner_update", [sys.executable, str(learner_script), *(["--quick"] if args.quick else [])])
        if learner is None:
            failed.append("learner_update")
        else:
            s = learner["summary"]
            line = (f"   PPO update: NF {s['nf_update_s']:.2f} s, MLP {s['mlp_update_s']:.2f} s "
                    f"({s['update_nf_over_mlp']:.2f}x)")
            if "iteration_nf_over_mlp" in s:
                line += (f"; training iteration NF {s['iteration_nf_s']:.2f} s, MLP {s['iteration_mlp_s']:.2f} s: "
                         f"{s['iteration_nf_over_mlp']:.2f}x (target <= {s['target_iteration_max']}x)")
                if "iteration_sb3_s" in s:
                    line += (f"; stable-baselines3 PPO {s['iteration_sb3_s']:.2f} s: NF/SB3 "
                             f"{s['iteration_nf_over_sb3']:.2f}x (target <= {s['target_nf_over_sb3_max']}x)")
                elif "sb3_skipped" in s:
                    line += f"; stable-baselines3 PPO SKIPPED: {s['sb3_skipped']}"
            print(line)
    quick = ["--quick"] if args.quick else []
    overhead = _run("episode_overhead", [sys.executable, str(HERE / "episode_overhead.py"), *quick])
    if overhead is None:
        failed.append("episode_overhead")
    else:
        w = overhead["wall_ratio"]
        print(f"   composed loop (no ROS) over the in-process rollout, same episodes: median {w['median']:.3f}x "
              f"(quartiles {w['p25']:.3f}-{w['p75']:.3f}, {len(w['all'])} pairs)")
    for name, script, summary in _ROS_BENCHMARKS:
        result = _run(name, [sys.executable, str(HERE / script), *quick])
        if result is None:
            failed.append(name)
        else:
            print(summary(result))
    if failed:
        print(f"failed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
