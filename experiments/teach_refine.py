"""Teach, fit, refine on gear_clamp: the table of docs/results/teach (issue 46).

1. ``teach``: N demonstrations by the scripted operator through the stable law (one bag).
2. ``fit_demos``: the flow fitted to the recorded paths, the prior evaluated on the 10 held-out starts.
3. ``train_cli`` from that checkpoint with config/gear_clamp.yaml, for each seed: flow + gains (the flow
   explored along the demonstrations' directions) and gains only (the flow frozen: param_sigma_flow 0),
   evaluated every 5 iterations and at the end, deterministic on the same held-out starts.
Without ``--demos``: learning from the identity flow (no demonstrations), flow + gains, for each seed.

    python experiments/teach_refine.py --out /tmp/teach_refine [--demos 10] [--seeds 0 1 2] [--iterations 20]
    python experiments/teach_refine.py --out /tmp/identity --demos 0 --iterations 30

Writes ``<out>/results.json`` and prints a markdown table. Runs one process at a time (about 1 min per
learning run here, 2 min for the teaching).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_clamp.yaml"
VARIANTS = {"flow + gains": [], "gains only (flow frozen)": ["--set", "param_sigma_flow=0"]}


def run(cmd: list[str], log: Path) -> None:
    """Run ``cmd``, its output to ``log``; raise with the log's tail if it fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as fh:
        done = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=os.environ.copy())
    if done.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{log.read_text()[-2000:]}")


def inserted(path: Path) -> int | None:
    """Deterministic successes in an evaluation file (None if missing)."""
    if not path.exists():
        return None
    data = json.loads(path.read_text())
    return int(round(data["success_rate"] * data["episodes"]))


def learn(out: Path, seed: int, iterations: int, extra: list[str]) -> dict:
    """One train_cli run; its prior, periodic and final deterministic evaluations and training success."""
    run([sys.executable, "-m", "learner_node.train_cli", "--config", str(CONFIG), "--seed", str(seed),
         "--iterations", str(iterations), "--out", str(out), "--fresh", "--no-progress",
         "--set", "eval_every=5", *extra], out.with_suffix(".log"))
    rows = json.loads((out / "metrics.json").read_text())
    periodic = {int(p.stem.split("_")[-1]): inserted(p) for p in sorted((out / "evaluations").glob("iteration_*.json"))}
    return {"prior": inserted(out / "evaluation_prior.json"), "periodic": periodic,
            "final": inserted(out / "evaluation.json"),
            "training_success": [round(r["success_rate"], 2) for r in rows],
            "final_S": [round(rows[-1][f"stiffness_{k}"]) for k in range(3)],
            "final_D": [round(rows[-1][f"damping_{k}"]) for k in range(3)]}


def flow_change(out: Path, png: Path | None) -> dict:
    """How far refinement moved each flow + gains run's flow from the fitted prior (normalised weights, the
    units learning explores), and V before and after (seed 0 of each variant) on the held-out starts."""
    import numpy as np
    from nf_bags.fit_demos import demo_paths, evaluate, gains_text, plot_landscape

    from learner_node.analysis.flow_landscape import load_policy
    from learner_node.config import TrainConfig
    from learner_node.flow import rescale_flow_weights
    from learner_node.trainer import Trainer
    from nf_core.task_spec import load_task

    cfg = TrainConfig.from_sources(CONFIG, {"init_checkpoint": str(out / "fit" / "checkpoint.pt")})
    prior = Trainer(cfg)
    prior.resume_or_init()
    pol0 = prior.policy
    x_ref = pol0.x_ref.numpy()

    def normalised(pol: object) -> np.ndarray:
        return rescale_flow_weights(pol.arch, pol.flow.to_flat(), x_ref, cfg.flow_input_scale, inverse=True)

    w0 = normalised(pol0)
    moved, columns = {}, [(f"fitted prior, {gains_text(pol0)}", pol0, evaluate(prior, pol0, 10))]
    for run in sorted(out.glob("*_s[0-9]*")):
        if not (run / "checkpoint.pt").exists():
            continue
        _, pol = load_policy(run)
        moved[run.name] = round(float(np.linalg.norm(normalised(pol) - w0)), 4)
        if run.name.endswith("_s0"):
            columns.append((f"{run.name} after refinement, {gains_text(pol)}", pol, evaluate(prior, pol, 10)))
    if png is not None:
        task = load_task(cfg.task)
        plot_landscape(png, task, columns, demo_paths(out / "teach" / "bag", task))
    return {"flow_weight_change_norm": moved}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--demos", type=int, default=10, help="demonstrations to record (0: from the identity flow)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--report-only", action="store_true",
                    help="only the flow's change and the picture (<out>/landscape.png) from the runs already in --out")
    args = ap.parse_args()
    out = args.out.resolve()
    if args.report_only:
        change = flow_change(out, out / "landscape.png")
        print(json.dumps(change))
        data = json.loads((out / "results.json").read_text())
        data["flow_change"] = change["flow_weight_change_norm"]
        (out / "results.json").write_text(json.dumps(data, indent=1) + "\n")
        return
    results: dict = {"demos": args.demos, "iterations": args.iterations, "runs": {}}
    variants = VARIANTS
    if args.demos:
        run([sys.executable, "-m", "nf_bringup.teach", "--demos", str(args.demos), "--out", str(out / "teach")],
            out / "teach.log")
        results["teach"] = json.loads((out / "teach" / "demos.json").read_text())
        run([sys.executable, "-m", "nf_bags.fit_demos", str(out / "teach" / "bag"), "--config", str(CONFIG),
             "--out", str(out / "fit")], out / "fit.log")
        results["fit"] = json.loads((out / "fit" / "fit.json").read_text())
        init = ["--set", f"init_checkpoint={out / 'fit' / 'checkpoint.pt'}"]
    else:
        init, variants = [], {"flow + gains, identity flow": []}
    for name, extra in variants.items():
        for seed in args.seeds:
            key = f"{name}, seed {seed}"
            results["runs"][key] = learn(out / f"{'gains' if 'frozen' in name else 'flow'}_s{seed}", seed,
                                         args.iterations, [*init, *extra])
            r = results["runs"][key]
            print(f"{key}: prior {r['prior']}/10, every 5: {r['periodic']}, final {r['final']}/10", flush=True)
            (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    if args.demos:
        results["flow_change"] = flow_change(out, out / "landscape.png")["flow_weight_change_norm"]
        (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    print("\n| run | prior | at 5, 10, 15, ... | final (of 10) | training success min / mean | final S | final D |")
    print("|---|---|---|---|---|---|---|")
    for key, r in results["runs"].items():
        ts = r["training_success"]
        print(f"| {key} | {r['prior']} | {', '.join(str(v) for v in r['periodic'].values())} | **{r['final']}** | "
              f"{min(ts):.2f} / {sum(ts) / len(ts):.2f} | {r['final_S']} | {r['final_D']} |")


if __name__ == "__main__":
    main()
