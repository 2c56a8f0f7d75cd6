"""Do task files a user writes learn with the shipped learner settings? Runs ``make run``'s stack
(config/gear_learn.yaml, 30 iterations, lockstep) on each example task file for each seed, one run at a
time, and prints the table of docs/results/task_files.md: prior and learned deterministic success (10
held-out starts), the 90 % window (first iteration where the 5-iteration mean training success >= 0.9).

    python experiments/task_files_learn.py [--seeds 0 1 2] [--files F ...] [--out runs/task_files]

A run folder that already holds an evaluation is read, not run again.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

from learner_node.analysis.report import iterations_to_success

FILES = sorted(Path("config/tasks/examples").glob("*.yaml"))


def run(task: Path, seed: int, out: Path) -> float:
    """One ``make run`` of ``task`` with ``seed`` into ``out`` (skipped when done); its wall time (s)."""
    if (out / "learner" / "evaluation.json").exists():
        return float("nan")
    cmd = [sys.executable, "-m", "nf_bringup.stack", "--config", "config/gear_learn.yaml", "--task", str(task),
           "--out", str(out), "--no-video", "--learner-arg=-p", f"--learner-arg=learner_node:seed:={seed}"]
    t0 = time.monotonic()
    print(f"[task_files] {' '.join(cmd)}", flush=True)
    with open(out.parent / f"{out.name}.log", "w") as log:
        subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, check=True)
    return time.monotonic() - t0


def row(task: Path, seed: int, out: Path, wall: float) -> str:
    """The table row of one finished run."""
    learner = out / "learner"
    metrics = json.loads((learner / "metrics.json").read_text())
    success = [m["success_rate"] for m in metrics]
    window = iterations_to_success(success)
    prior = json.loads((learner / "evaluation_prior.json").read_text())
    final = json.loads((learner / "evaluation.json").read_text())
    ok0, ok = (sum(e["success"] for e in ev["per_episode"]) for ev in (prior, final))
    n = final["episodes"]
    wall_text = "" if wall != wall else f"{wall / 60:.1f}"
    return (f"| {task.stem} | {seed} | {ok0}/{n} | {ok}/{n} | {'not reached' if window == math.inf else int(window)} | "
            f"{len(success)} | {1e3 * final['final_distance_mean']:.1f} | {wall_text} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=Path, nargs="+", default=FILES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=Path("runs/task_files"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = ["| task file | seed | prior (det.) | learned (det.) | 90 % window | iterations | final distance (mm) "
            "| minutes |", "|---|---|---|---|---|---|---|---|"]
    for task in args.files:
        for seed in args.seeds:
            out = args.out / f"{task.stem}-s{seed}"
            wall = run(task, seed, out)
            rows.append(row(task, seed, out, wall))
            print(rows[-1], flush=True)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
