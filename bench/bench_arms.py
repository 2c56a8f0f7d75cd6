"""Scaling with the number of arms: one learner dispatching to N composed arm stacks (``/arm0`` ..),
N = 1, 2, 4, on this machine.

1. realtime arms (``sim_bridge:mode: realtime``: 1 kHz wall clock, a real arm's pace): the wall time
   of one learner iteration (``rollout_seconds + update_seconds``; ideal: rollouts x episode length / N)
   and the CPU of every arm process over it (``/proc/<pid>/stat`` utime+stime from the learner's
   "NF-PPO over ROS" line to its "iteration 1/1" line, which includes its wait for the arms'
   policy subscriptions: ``cpu_window_s``), and the learner's;
2. lockstep arms (as ``make run``): throughput, simulated steps per wall second summed over the arms.

Each N runs ``--repeats`` times (fresh processes, own ROS_DOMAIN_ID, loopback only); medians over the
repeats and the ratio to N = 1. The settings are ``config/gear_learn.yaml``'s (parameter exploration)
with 8 rollouts of 2 s (``--quick``: 4 rollouts of 1 s, N = 1, 2, one repeat: a smoke run, not a
result). ``where_cores_run_out`` says at which N the processes needed more cores than the machine has
or the lockstep throughput stopped growing. Writes ``bench/results/arms.json``; run it on a quiet
machine (other load changes everything here).
Usage: python bench/bench_arms.py [--quick] [--repeats 3] [--arms 1 2 4]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import sources  # noqa: F401  (the package sources first on sys.path)

from nf_bringup.processes import ManagedProcess, allocate_domain_id, ros_env

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CONFIG = REPO / "config" / "gear_learn.yaml"
SIM_DT = 0.001  # s of simulated time per sim step
TICK = os.sysconf("SC_CLK_TCK")
# per mode, a second parameters file: ``-p node:x:=v`` does not reach a namespaced node, and a plain
# ``-p`` loses to the config's ``/**/<node>`` sections
MODE_PARAMS = {
    "lockstep": "/**/nf_controller:\n  ros__parameters:\n    idle_mode: pause\n    max_consecutive_misses: 0\n",
    "realtime": "/**/sim_bridge:\n  ros__parameters:\n    mode: realtime\n",
}
ITERATION_START = "NF-PPO over ROS on"
ITERATION_END = "iteration   1/1"


def cpu_seconds(pid: int) -> float:
    """utime + stime of ``pid`` in s (0.0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TICK  # fields 14 and 15 of proc(5), after "pid (comm)"


class CpuWindow:
    """CPU seconds of some processes between two events of the learner's output (``mark``)."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = pids
        self.marks: dict[str, tuple[float, dict[str, float]]] = {}
        self.done = threading.Event()

    def mark(self, name: str) -> None:
        self.marks[name] = (time.monotonic(), {k: cpu_seconds(p) for k, p in self.pids.items()})
        if name == "end":
            self.done.set()

    def on_line(self, line: str) -> None:
        if ITERATION_START in line and "start" not in self.marks:
            self.mark("start")
        elif ITERATION_END in line:
            self.mark("end")

    def result(self) -> dict:
        (t0, c0), (t1, c1) = self.marks["start"], self.marks["end"]
        wall = t1 - t0
        return {"window_s": wall, "cpu_s": {k: c1[k] - c0[k] for k in c0},
                "cores": {k: (c1[k] - c0[k]) / wall for k in c0}}


def one_round(mode: str, n: int, rollouts: int, seconds: float, work: Path) -> dict:
    """N arms in ``mode`` and a learner doing one iteration; its metrics and the processes' CPU."""
    domain = allocate_domain_id()
    env = ros_env(domain)
    run = work / f"{mode}{n}-{domain}"
    run.mkdir(parents=True)
    extra = run / "mode.yaml"
    extra.write_text(MODE_PARAMS[mode])
    namespaces = [f"/arm{i}" for i in range(n)]
    params = ["--ros-args", "--params-file", str(CONFIG), "--params-file", str(extra)]
    arms = [ManagedProcess(ns[1:], [sys.executable, "-m", "nf_bringup.sim_stack", *params, "-r", f"__ns:={ns}"], env,
                           run / "logs", echo=False) for ns in namespaces]
    learner = None
    try:
        listed = "[" + ",".join(f"'{ns}'" for ns in namespaces) + "]"
        argv = [sys.executable, "-m", "learner_node.node", *params, "-p", "learner_node:on_safe_hold:=auto",
                "-p", f"learner_node:out_dir:={run / 'learner'}", "-p", "learner_node:iterations:=1",
                "-p", f"learner_node:rollouts_per_iter:={rollouts}", "-p", "learner_node:eval_episodes:=0",
                "-p", "learner_node:evaluate_prior:=false", "-p", f"learner_node:arms:={listed}",
                "-p", "learner_node:discover_arms:=false", "-p", f"episode_seconds:={seconds}"]
        window = CpuWindow({a.name: a.pid for a in arms})
        learner = ManagedProcess("learner", argv, env, run / "logs", echo=False, on_line=window.on_line)
        window.pids["learner"] = learner.pid
        deadline = time.monotonic() + 600.0
        while learner.running() and time.monotonic() < deadline:
            time.sleep(0.2)
        code = learner.stop(10.0)
        if code != 0 or "end" not in window.marks:
            raise RuntimeError(f"{mode} N={n}: learner exit {code}; see {run / 'logs'}")
        row = json.loads((run / "learner" / "metrics.json").read_text())[-1]
    finally:
        if learner is not None:
            learner.stop(10.0)
        for a in reversed(arms):
            a.stop(10.0)
    cpu = window.result()
    arm_cores = [cpu["cores"][a.name] for a in arms]
    wall = row["rollout_seconds"] + row["update_seconds"]
    return {"iteration_wall_s": wall, "rollout_s": row["rollout_seconds"], "update_s": row["update_seconds"],
            "ideal_rollout_s": rollouts * seconds / n,
            "steps_per_s": rollouts * seconds / SIM_DT / row["rollout_seconds"],
            "arm_cpu_cores": arm_cores, "arm_cpu_cores_mean": statistics.fmean(arm_cores),
            "learner_cpu_cores": cpu["cores"]["learner"], "cores_used": sum(cpu["cores"].values()),
            "cpu_window_s": cpu["window_s"], "arm_cpu_s": [cpu["cpu_s"][a.name] for a in arms],
            "rerun_episodes": row.get("rerun_episodes", 0.0), "arms_used": row.get("arms_used", float(n)),
            "success_rate": row["success_rate"]}


def median_of(rounds: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rounds)


def where_cores_run_out(out: dict, cores: int) -> str:
    """A sentence: the first N whose processes needed (nearly) all cores, and the first N whose lockstep
    throughput grew less than 3/4 of N's growth (1.5x per doubling)."""
    notes = []
    rt = out["realtime"]
    full = [n for n in rt if rt[n]["cores_used_median"] >= 0.9 * cores]
    if full:
        n = full[0]
        notes.append(f"realtime: at N={n} the arms and the learner used {rt[n]['cores_used_median']:.2f} of {cores} "
                     f"cores (an arm {rt[n]['arm_cpu_cores_median']:.2f} of a core: its 1 kHz loop, awake "
                     f"{'spinning' if rt[n]['arm_cpu_cores_median'] > 0.5 else 'per tick'}); its iteration took "
                     f"{rt[n]['iteration_wall_ratio_to_1']:.2f}x N=1's (ideal {1 / int(n):.2f}x)")
    else:
        notes.append(f"realtime: up to N={max(rt, key=int)} the processes stayed below {0.9 * cores:.1f} of "
                     f"{cores} cores")
    ls = out["lockstep"]
    ns = sorted(ls, key=int)
    flat = [b for a, b in itertools.pairwise(ns)
            if ls[b]["steps_per_s_median"] < 0.75 * ls[a]["steps_per_s_median"] * int(b) / int(a)]
    if flat:
        used = ls[flat[0]]["cores_used_median"]
        why = (f"the processes used {used:.2f} of {cores} cores: the cores ran out (a lockstep arm steps as fast as "
               f"its core lets it)" if used >= 0.9 * cores else
               f"yet the processes used only {used:.2f} of {cores} cores: not the cores here but the handover "
               f"between episodes or other load on the machine")
        notes.append(f"lockstep: from N={flat[0]} the summed throughput grew less than 1.5x per doubling "
                     f"({ls[flat[0]]['steps_per_s_ratio_to_1']:.2f}x N=1's); {why}")
    else:
        notes.append(f"lockstep: the summed throughput grew with N up to N={ns[-1]} "
                     f"({ls[ns[-1]]['steps_per_s_ratio_to_1']:.2f}x N=1's)")
    return "; ".join(notes)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N = 1, 2; 4 rollouts of 1 s; one repeat (smoke run)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--arms", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=2.0, help="episode length (s of simulated time)")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "arms.json")
    args = parser.parse_args()
    if args.quick:
        args.repeats, args.arms, args.rollouts, args.seconds = 1, [1, 2], 4, 1.0
    cores = os.cpu_count() or 1
    out: dict = {"benchmark": "one learner, N composed arms: realtime iteration wall time and CPU per arm, "
                              "lockstep summed throughput",
                 "command": "python bench/bench_arms.py" + (" --quick" if args.quick else ""),
                 "quick": args.quick, "machine": {"cpus": cores, "platform": platform.platform(),
                                                  "loadavg_before": os.getloadavg()},
                 "config": str(CONFIG.relative_to(REPO)), "rollouts": args.rollouts, "episode_seconds": args.seconds,
                 "repeats": args.repeats}
    with tempfile.TemporaryDirectory(prefix="bench_arms_") as tmp:
        for mode in ("realtime", "lockstep"):
            per_n: dict[str, dict] = {}
            for n in args.arms:
                rounds = []
                for rep in range(args.repeats):
                    r = one_round(mode, n, args.rollouts, args.seconds, Path(tmp))
                    ideal = f" (ideal rollouts {r['ideal_rollout_s']:.1f} s)" if mode == "realtime" else ""
                    print(f"[bench_arms] {mode} N={n} #{rep + 1}: iteration {r['iteration_wall_s']:.2f} s{ideal}, "
                          f"{r['steps_per_s']:.0f} steps/s summed, CPU per "
                          f"arm {r['arm_cpu_cores_mean']:.2f} cores, all {r['cores_used']:.2f}, reruns "
                          f"{r['rerun_episodes']:.0f}", flush=True)
                    rounds.append(r)
                per_n[str(n)] = {"rounds": rounds, **{f"{k}_median": median_of(rounds, k) for k in (
                    "iteration_wall_s", "rollout_s", "steps_per_s", "arm_cpu_cores_mean", "learner_cpu_cores",
                    "cores_used", "rerun_episodes")}}
                per_n[str(n)]["arm_cpu_cores_median"] = per_n[str(n)].pop("arm_cpu_cores_mean_median")
            first = per_n[str(args.arms[0])]
            for v in per_n.values():
                v["iteration_wall_ratio_to_1"] = v["iteration_wall_s_median"] / first["iteration_wall_s_median"]
                v["steps_per_s_ratio_to_1"] = v["steps_per_s_median"] / first["steps_per_s_median"]
            out[mode] = per_n
    out["machine"]["loadavg_after"] = os.getloadavg()
    out["where_cores_run_out"] = where_cores_run_out(out, cores)
    print(f"[bench_arms] {out['where_cores_run_out']}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(f"[bench_arms] wrote {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
