"""Where the time between two episodes goes over ROS: a trace of the hand-over in the composed stack.

Runs the learner's first gear iteration (``make run``'s settings, 15 rollouts) against the composed
stack (``nf_sim_stack``, lockstep), both as separate processes (own ROS_DOMAIN_ID, loopback only)
with a small tracing prelude: named methods are wrapped to write a monotonic timestamp when they
are entered and left (``time.monotonic`` is one clock for all processes). From the trace, for every
episode after the first: the driver idle between the end of one episode and the start of the next
(``handover``), split into its steps:

- ``end_to_result``: the episode's last tick -> the learner has the result and every chunk
- ``learner_turnaround``: the learner's bookkeeping and the next rollout's parameters -> goal sent
- ``spin_lock_wait``: part of the turnaround, the wait for the learner's executor (``SpinLock``)
- ``goal_to_controller``: goal sent -> the controller's goal callback
- ``setup_and_reset``: goal callback -> the driver starts the episode (policy check, world reset)

Medians over all hand-overs of ``--repeats`` iterations; writes ``bench/results/handover.json``.
The tracing itself adds a few microseconds per wrapped call (a line written to a file).
Usage: python bench/trace_handover.py [--repeats 2] [--rollouts 15] [--quick]
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
CONFIG = HERE.parent / "config" / "gear_learn.yaml"

# what each process traces: module, class, method
STACK = [("nf_controller_node.host", "ControllerHost", "start_episode"),
         ("nf_controller_node.host", "ControllerHost", "end_episode"),
         ("nf_controller_node.node", "NFControllerNode", "_on_goal"),
         ("nf_controller_node.node", "NFControllerNode", "_report")]
LEARNER = [("learner_node.node", "LearnerNode", "run_episode"),
           ("nf_controller_node.ros_runtime", "SpinLock", "__enter__"),
           ("rclpy.action.client", "ActionClient", "send_goal_async")]

PRELUDE = """
import functools, importlib, sys, time
_out = open(sys.argv.pop(1), "w", buffering=1)
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
sys.exit(importlib.import_module(sys.argv.pop(1)).main(sys.argv))  # the module's own main, as its script
"""


def _traced(module: str, trace: list[tuple[str, str, str]], log: Path, args: list[str]) -> list[str]:
    spec = ",".join(":".join(t) for t in trace)
    return [sys.executable, "-c", PRELUDE, str(log), spec, module, *args]


def run_iteration(domain: int, workdir: Path, rollouts: int, config: Path) -> tuple[Path, Path, dict]:
    """One learner iteration against the composed stack, both traced; (stack log, learner log, metrics row)."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    params = ["--ros-args", "--params-file", str(config)]
    stack_log, learner_log = workdir / f"stack{domain}.txt", workdir / f"learner{domain}.txt"
    stack = subprocess.Popen(
        _traced("nf_bringup.sim_stack", STACK, stack_log,
                [*params, "-p", "nf_controller:idle_mode:=pause", "-p", "nf_controller:max_consecutive_misses:=0"]),
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        out = workdir / f"run{domain}"
        learner = subprocess.run(
            _traced("learner_node.node", LEARNER, learner_log,
                    [*params, "-p", f"learner_node:out_dir:={out}", "-p", "learner_node:iterations:=1",
                     "-p", f"learner_node:rollouts_per_iter:={rollouts}", "-p", "learner_node:eval_episodes:=0",
                     "-p", "learner_node:evaluate_prior:=false"]),
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=900)
        if learner.returncode != 0:
            raise RuntimeError(f"learner exited with {learner.returncode}: {learner.stderr[-2000:]}")
        return stack_log, learner_log, json.loads((out / "metrics.json").read_text())[-1]
    finally:  # stopped by PID
        stack.send_signal(2)
        try:
            stack.wait(10)
        except subprocess.TimeoutExpired:
            stack.kill()


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
    reports = s["NFControllerNode._report out"]
    goals_in = s["NFControllerNode._on_goal in"]
    done = le["LearnerNode.run_episode out"]
    sent = le["ActionClient.send_goal_async in"]
    lock_in, lock_out = le["SpinLock.__enter__ in"], le["SpinLock.__enter__ out"]
    rows = []
    for k in range(len(ends) - 1):  # episode k ends, episode k + 1 starts
        end, nxt = ends[k], starts[k + 1]
        send = next(t for t in sent if t > end)
        waits = [b - a for a, b in zip(lock_in, lock_out, strict=True) if done[k] <= a <= send]
        rows.append({
            "handover": nxt - end,
            "end_to_result": done[k] - end,
            "controller_report": next(t for t in reports if t > end) - end,
            "learner_turnaround": send - done[k],
            "spin_lock_wait": sum(waits),
            "goal_to_controller": next(t for t in goals_in if t > send) - send,
            "setup_and_reset": nxt - next(t for t in goals_in if t > send),
        })
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2, help="traced iterations")
    parser.add_argument("--rollouts", type=int, default=15)
    parser.add_argument("--config", type=Path, default=CONFIG)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "handover.json")
    parser.add_argument("--quick", action="store_true", help="one iteration of 5 rollouts")
    args = parser.parse_args()
    if args.quick:
        args.repeats, args.rollouts = 1, 5
    rows, walls = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            domain = 150 + (os.getpid() + r) % 50
            print(f"[handover] iteration {r + 1}/{args.repeats} (ROS_DOMAIN_ID {domain}) ...", flush=True)
            stack_log, learner_log, metrics = run_iteration(domain, Path(tmp), args.rollouts, args.config)
            rows += handovers(stack_log, learner_log)
            walls.append(metrics["rollout_seconds"])
    keys = list(rows[0])
    result = {
        "benchmark": "handover", "date": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": platform.machine(),
        "cpus": os.cpu_count(), "config": str(args.config), "rollouts": args.rollouts, "repeats": args.repeats,
        "handovers": len(rows), "rollout_seconds": walls,
        "median_ms": {k: 1e3 * statistics.median(r[k] for r in rows) for k in keys},
        "p90_ms": {k: 1e3 * sorted(r[k] for r in rows)[int(0.9 * (len(rows) - 1))] for k in keys},
        "max_ms": {k: 1e3 * max(r[k] for r in rows) for k in keys},
        "share_of_rollouts": sum(r["handover"] for r in rows) / sum(walls),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"{len(rows)} hand-overs; milliseconds: median / p90 / max")
    for k in keys:
        print(f"  {k:20s} {result['median_ms'][k]:6.2f} / {result['p90_ms'][k]:6.2f} / {result['max_ms'][k]:6.2f}")
    print(f"hand-overs: {100 * result['share_of_rollouts']:.1f} % of the rollout time; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
