"""Where a PPO iteration over ROS spends its time beyond the driver loop's own work: a trace.

Runs the learner's first gear iteration (``make run``'s settings, 15 rollouts) against the composed
stack (``nf_sim_stack``, lockstep), both as separate processes (own ROS_DOMAIN_ID, loopback only)
with a small tracing prelude: named methods write a monotonic timestamp when they are entered and
left (``time.monotonic`` and ``time.perf_counter`` are one clock for all processes on Linux), and the
sim's ``step_with`` records the time of every physics step. Then, in this process, the same
iteration's episodes through the composed driver loop without ROS (``bench_stack.loop_alone_iteration``),
steps recorded the same way: the baseline of the same run.

Two results:

- The hand-over between two episodes (the driver idle from one episode's last tick to the next one's
  first), split: ``end_to_result`` (last tick -> the learner has the result and every chunk;
  ``controller_report``: -> the controller's result callback), ``learner_turnaround`` (-> next goal
  sent; ``spin_lock_wait``: the learner's wait for its executor), ``goal_to_controller``,
  ``setup_and_reset`` (goal callback -> the driver starts the episode).
- Stalls inside episodes: steps that took more than 3x the median step, their time beyond the
  median summed (``stall_excess_ms``), and for the ROS run which executor callback of the
  controller's process overlapped them (the executor thread takes the GIL from the driver thread).

Writes ``bench/results/ros_iteration_trace.json``. The tracing adds a few microseconds per traced
call (a line written to a file) and ~0.3 us per step.
Usage: python bench/trace_ros_iteration.py [--repeats 2] [--rollouts 15] [--quick] [--stack-param NODE:NAME:=VALUE]
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

import numpy as np
import sources  # noqa: F401  (the package sources first on sys.path)

from nf_bringup.processes import RosProcess, allocate_domain_id, ros_env

HERE = Path(__file__).resolve().parent
CONFIG = HERE.parent / "config" / "gear_learn.yaml"
STALL_OVER_MEDIAN = 3.0  # a step that takes longer than this times the median step is a stall
IN_EPISODE = 2e-3  # s, a gap between two steps longer than this is between episodes

# what each process traces: module, class, method
_NODE = "nf_controller_node.node"
EXECUTOR_CALLBACKS = [(_NODE, "NFControllerNode", m) for m in (
    "_publish_status", "_publish_feedback", "_publish_diagnostics", "_drain", "_on_policy", "_on_goal",
    "_on_accepted", "_advance_setup", "_report")] + [("sim_bridge_node.node", "SimBridgeNode", "_publish_diagnostics")]
STACK = [("nf_controller_node.host", "ControllerHost", "start_episode"),
         ("nf_controller_node.host", "ControllerHost", "end_episode"), *EXECUTOR_CALLBACKS]
LEARNER = [("learner_node.node", "LearnerNode", "run_episode"),
           ("nf_core.ros_runtime", "SpinLock", "__enter__"),
           ("rclpy.action.client", "ActionClient", "send_goal_async")]

# argv after -c: trace log, step log ("-": none), traced methods, module whose main() to run, its args
PRELUDE = """
import atexit, functools, importlib, os, sys, time
_out = open(sys.argv.pop(1), "w", buffering=1)
_steps_path = sys.argv.pop(1)
def _wrap(mod, cls, name):
    owner = getattr(importlib.import_module(mod), cls)
    fn = getattr(owner, name)
    @functools.wraps(fn)
    def traced(*a, **k):
        _out.write(f"{time.monotonic():.6f} {cls}.{name} in\\n")
        try:
            return fn(*a, **k)
        finally:
            _out.write(f"{time.monotonic():.6f} {cls}.{name} out\\n")
    setattr(owner, name, traced)
for _spec in sys.argv.pop(1).split(","):
    _wrap(*_spec.split(":"))
if _steps_path != "-":
    sys.path.insert(0, os.path.dirname(_steps_path.split("::")[0]))
    import trace_ros_iteration
    atexit.register(trace_ros_iteration.record_steps(), _steps_path.split("::")[1])
sys.exit(importlib.import_module(sys.argv.pop(1)).main(sys.argv))  # the module's own main, as its script
"""


def record_steps(capacity: int = 4_000_000):
    """Record the time of every ``SimBridge.step_with`` in this process; returns ``save(path)``."""
    from sim_bridge_node.bridge import SimBridge

    stamps = np.zeros(capacity)
    count = [0]
    step_with, clock = SimBridge.step_with, time.perf_counter

    def recorded(self, tau):
        i = count[0]
        if i < capacity:
            stamps[i] = clock()
            count[0] = i + 1
        return step_with(self, tau)

    SimBridge.step_with = recorded
    return lambda path: np.save(path, stamps[:count[0]])


def _traced(module: str, trace: list[tuple[str, str, str]], log: Path, steps: Path | None,
            args: list[str]) -> list[str]:
    spec = ",".join(":".join(t) for t in trace)
    steps_arg = f"{Path(__file__).resolve()}::{steps}" if steps else "-"  # this module (record_steps), the log
    return ["-c", PRELUDE, str(log), steps_arg, spec, module, *args]


def run_iteration(domain: int, workdir: Path, rollouts: int, config: Path, stack_params: list[str] = ()) -> dict:
    """One learner iteration against the composed stack, both traced: paths of the logs and the metrics row."""
    params = ["--ros-args", "--params-file", str(config)]
    logs = {"stack": workdir / f"stack{domain}.txt", "learner": workdir / f"learner{domain}.txt",
            "steps": workdir / f"steps{domain}.npy"}
    stack = RosProcess(
        _traced("nf_bringup.sim_stack", STACK, logs["stack"], logs["steps"],
                [*params, "-p", "nf_controller:idle_mode:=pause", "-p", "nf_controller:max_consecutive_misses:=0",
                 *(a for p in stack_params for a in ("-p", p))]), domain)
    try:
        out = workdir / f"run{domain}"
        learner_args = [*params, "-p", f"learner_node:out_dir:={out}", "-p", "learner_node:iterations:=1",
                        "-p", f"learner_node:rollouts_per_iter:={rollouts}", "-p", "learner_node:eval_episodes:=0",
                        "-p", "learner_node:evaluate_prior:=false"]
        learner = subprocess.run(
            [sys.executable, *_traced("learner_node.node", LEARNER, logs["learner"], None, learner_args)],
            env=ros_env(domain), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=900)
        if learner.returncode != 0:
            raise RuntimeError(f"learner exited with {learner.returncode}: {learner.stderr[-2000:]}")
        metrics = json.loads((out / "metrics.json").read_text())[-1]
    finally:  # its exit writes the step log
        stack.stop(20.0)
    return {**logs, "metrics": metrics}


def _events(log: Path) -> dict[str, list[float]]:
    """"Class.method in|out" -> its timestamps, in order."""
    events: dict[str, list[float]] = {}
    for line in log.read_text().splitlines():
        t, name, edge = line.split()
        events.setdefault(f"{name} {edge}", []).append(float(t))
    return events


def handovers(stack_log: Path, learner_log: Path) -> list[dict[str, float]]:
    """The steps of every hand-over in one traced iteration (seconds)."""
    s, le = _events(stack_log), _events(learner_log)
    ends, starts = s["ControllerHost.end_episode in"], s["ControllerHost.start_episode in"]
    reports, goals_in = s["NFControllerNode._report out"], s["NFControllerNode._on_goal in"]
    done, sent = le["LearnerNode.run_episode out"], le["ActionClient.send_goal_async in"]
    lock_in, lock_out = le["SpinLock.__enter__ in"], le["SpinLock.__enter__ out"]
    rows = []
    for k in range(len(ends) - 1):  # episode k ends, episode k + 1 starts
        end, nxt = ends[k], starts[k + 1]
        send = next(t for t in sent if t > end)
        goal = next(t for t in goals_in if t > send)
        rows.append({
            "handover": nxt - end,
            "end_to_result": done[k] - end,
            "controller_report": next(t for t in reports if t > end) - end,
            "learner_turnaround": send - done[k],
            "spin_lock_wait": sum(b - a for a, b in zip(lock_in, lock_out, strict=True) if done[k] <= a <= send),
            "goal_to_controller": goal - send,
            "setup_and_reset": nxt - goal,
        })
    return rows


def _callbacks(stack_log: Path) -> list[tuple[float, float, str]]:
    """(start, end, name) of every traced executor callback."""
    names = {f"{c}.{m}" for _, c, m in EXECUTOR_CALLBACKS}
    opened: dict[str, float] = {}
    out = []
    for line in stack_log.read_text().splitlines():
        t, name, edge = line.split()
        if name not in names:
            continue
        if edge == "in":
            opened[name] = float(t)
        elif name in opened:
            out.append((opened.pop(name), float(t), name))
    return sorted(out)


def stalls(steps: np.ndarray, callbacks: list[tuple[float, float, str]] | None = None) -> dict:
    """In-episode step times of one run: median, total, stalls and (given the executor's callbacks)
    the stall time each callback overlapped."""
    gaps = np.diff(steps)
    inside = gaps[gaps < IN_EPISODE]
    median = float(np.median(inside))
    slow = np.where((gaps < IN_EPISODE) & (gaps > STALL_OVER_MEDIAN * median))[0]
    excess = gaps[slow] - median
    result = {"steps": int(inside.size), "in_episode_s": float(inside.sum()), "median_step_us": 1e6 * median,
              "mean_step_us": 1e6 * float(inside.mean()), "stalls": int(slow.size),
              "stall_excess_ms": 1e3 * float(excess.sum())}
    if callbacks is not None:
        starts = np.array([c[0] for c in callbacks])
        ends = np.array([c[1] for c in callbacks])
        by: dict[str, float] = {}
        for i, ex in zip(slow, excess, strict=True):
            hit = np.where((starts < steps[i + 1]) & (ends > steps[i]))[0]
            name = callbacks[hit[0]][2] if hit.size else "no traced callback"
            by[name] = by.get(name, 0.0) + 1e3 * float(ex)
        result["stall_excess_ms_by_overlap"] = dict(sorted(by.items(), key=lambda kv: -kv[1]))
        result["callbacks"] = {n: sum(1 for c in callbacks if c[2] == n) for n in sorted({c[2] for c in callbacks})}
    return result


def loop_alone_steps(rollouts: int, config: Path, path: Path) -> dict:
    """The iteration's episodes through the composed driver loop without ROS, steps recorded."""
    sys.path.insert(0, str(HERE))
    from bench_stack import loop_alone_iteration

    save = record_steps()
    run = loop_alone_iteration(rollouts, 5.0, config)
    save(path)
    return run


def _median_of(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2, help="traced iterations (each with its baseline)")
    parser.add_argument("--rollouts", type=int, default=15)
    parser.add_argument("--config", type=Path, default=CONFIG)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "ros_iteration_trace.json")
    parser.add_argument("--quick", action="store_true", help="one iteration of 5 rollouts")
    parser.add_argument("--stack-param", action="append", default=[], metavar="NODE:NAME:=VALUE",
                        help="a parameter for the composed stack, e.g. nf_controller:status_rate:=10.0 (repeatable)")
    args = parser.parse_args()
    if args.quick:
        args.repeats, args.rollouts = 1, 5
    rows, ros, alone, walls = [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            domain = allocate_domain_id()
            print(f"[trace] iteration {r + 1}/{args.repeats} over ROS (ROS_DOMAIN_ID {domain}) ...", flush=True)
            run = run_iteration(domain, Path(tmp), args.rollouts, args.config, args.stack_param)
            rows += handovers(run["stack"], run["learner"])
            ros.append(stalls(np.load(run["steps"]), _callbacks(run["stack"])))
            walls.append(run["metrics"]["rollout_seconds"])
            print(f"[trace] iteration {r + 1}/{args.repeats} without ROS ...", flush=True)
            steps_path = Path(tmp) / f"alone{r}.npy"
            loop_alone_steps(args.rollouts, args.config, steps_path)
            alone.append(stalls(np.load(steps_path)))
    keys = list(rows[0])
    overlap: dict[str, list[float]] = {}
    for run in ros:
        for name, ms in run["stall_excess_ms_by_overlap"].items():
            overlap.setdefault(name, []).append(ms)
    result = {
        "benchmark": "ros_iteration_trace", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": platform.machine(), "cpus": os.cpu_count(), "config": str(args.config),
        "rollouts": args.rollouts, "repeats": args.repeats, "stack_params": args.stack_param, "rollout_seconds": walls,
        "handover": {"count": len(rows),
                     "median_ms": {k: 1e3 * statistics.median(r[k] for r in rows) for k in keys},
                     "p90_ms": {k: 1e3 * sorted(r[k] for r in rows)[int(0.9 * (len(rows) - 1))] for k in keys},
                     "max_ms": {k: 1e3 * max(r[k] for r in rows) for k in keys},
                     "share_of_rollouts": sum(r["handover"] for r in rows) / sum(walls)},
        "in_episode": {"over_ros": ros, "without_ros": alone,
                       "stall_excess_ms_by_overlap_median": {k: statistics.median(v + [0.0] * (len(ros) - len(v)))
                                                             for k, v in overlap.items()}},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    h = result["handover"]
    print(f"{h['count']} hand-overs, milliseconds: median / p90 / max")
    for k in keys:
        print(f"  {k:20s} {h['median_ms'][k]:6.2f} / {h['p90_ms'][k]:6.2f} / {h['max_ms'][k]:6.2f}")
    print(f"hand-overs: {100 * h['share_of_rollouts']:.1f} % of the rollout time")
    print("inside episodes (medians over the repeats): over ROS / without ROS")
    for key, what in (("in_episode_s", "time in episodes, s"), ("median_step_us", "median step, us"),
                      ("mean_step_us", "mean step, us"), ("stall_excess_ms", "stall time beyond the median step, ms")):
        print(f"  {what:40s} {_median_of(ros, key):9.2f} / {_median_of(alone, key):9.2f}")
    print("  stall time over ROS by the executor callback it overlapped, ms:")
    for name, ms in result["in_episode"]["stall_excess_ms_by_overlap_median"].items():
        print(f"    {name:40s} {ms:7.1f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
