"""Do task files a user writes learn with the shipped learner settings? Runs ``make run``'s stack
(config/gear_learn.yaml, 30 iterations, lockstep) on each example task file for each seed, one run at a
time, and prints the table of docs/results/task_files.md: prior and learned deterministic success (10
held-out starts), the 90 % window (first iteration where the 5-iteration mean training success >= 0.9).

    python experiments/task_files_learn.py [--seeds 0 1 2] [--files F ...] [--out runs/task_files]

A run folder that already holds an evaluation is read, not run again.

    python experiments/task_files_learn.py --friction-probe runs/zero_shot/train_floor-s0/learner/checkpoint.pt ...

instead replays learned policies in the gear scene with joint Coulomb friction 0, 0.5 and 1 Nm on every
joint (6 held-out starts each) and prints where the TCP ends against the goal: the zero-shot section of
that page (why a policy learned without joint friction stops on the shaft's top).
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


def friction_probe(checkpoints: list[Path], coulombs: tuple[float, ...] = (0.0, 0.5, 1.0), starts: int = 6) -> None:
    """Each policy, deterministic, from held-out starts of the gear scene with that joint friction: success
    and the final TCP's offset from the goal (mm)."""
    import numpy as np

    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer, make_evaluator

    for ck in checkpoints:
        for c in coulombs:
            cfg = TrainConfig.from_sources("config/gear_learn.yaml", {
                "task": "gear", "friction_coulomb": [c, c], "friction_viscous": [0.0, 0.0], "init_checkpoint": str(ck)})
            trainer = Trainer(cfg)
            trainer.init_from_checkpoint(ck)
            evaluator = make_evaluator(trainer.policy)
            offsets, ok = [], 0
            for seed in range(1_000_000_000, 1_000_000_000 + starts):
                rec = trainer.runner.run_episode(evaluator, None, seed, None)
                offsets.append((rec.x[-1] - trainer.runner.goal) * 1e3)
                ok += bool(rec.final_success)
            o = np.array(offsets)
            print(f"{ck}: Coulomb {c:g} Nm: {ok}/{starts} inserted; TCP - goal (mm) x {o[:, 0].min():+.2f} to "
                  f"{o[:, 0].max():+.2f}, y {o[:, 1].min():+.2f} to {o[:, 1].max():+.2f}, z {o[:, 2].min():+.1f} to "
                  f"{o[:, 2].max():+.1f}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--friction-probe", type=Path, nargs="+", metavar="CHECKPOINT",
                    help="replay these policies with joint friction instead of learning")
    ap.add_argument("--files", type=Path, nargs="+", default=FILES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=Path("runs/task_files"))
    args = ap.parse_args()
    if args.friction_probe:
        friction_probe(args.friction_probe)
        return 0
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
