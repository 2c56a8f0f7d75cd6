"""Train in process and evaluate the deterministic controller every N iterations (held-out starts).

``python -m learner_node.analysis.checkpoint_evals --config config/gear_learn.yaml --seed 0
--iterations 50 --every 5 --out DIR [--set KEY=VALUE ...]``

The training is ``Trainer.run``'s (same seeds, same metrics and checkpoint in DIR); after every
``every``-th iteration the current policy's deterministic controller runs the same held-out starts
as the final evaluation, written to DIR/checkpoint_evals.json. Evaluations draw nothing from the
run's generator, so the training is the same as without them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from ..config import TrainConfig
from ..trainer import CHECKPOINT, Trainer


def main(argv: list[str] | None = None) -> None:
    """Command line (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    overrides = dict(kv.split("=", 1) for kv in args.set)
    overrides.update(seed=args.seed, iterations=args.iterations)
    cfg = TrainConfig.from_sources(args.config, overrides)
    trainer = Trainer(cfg, args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    evals = []
    if (args.out / CHECKPOINT).exists():  # resume (exactly, as train does) with the evaluations so far
        trainer.load_checkpoint(args.out / CHECKPOINT)
        if (args.out / "checkpoint_evals.json").exists():
            evals = json.loads((args.out / "checkpoint_evals.json").read_text())
    while trainer.iteration < cfg.iterations:
        trainer.train_iteration()
        trainer.write_metrics()
        trainer.save_checkpoint(args.out / CHECKPOINT)
        if trainer.iteration % args.every == 0:
            e = trainer.evaluate()
            evals.append({"iteration": trainer.iteration, "success_rate": e["success_rate"],
                          "final_distance_mean": e["final_distance_mean"], "torque_norm_mean": e["torque_norm_mean"]})
            (args.out / "checkpoint_evals.json").write_text(json.dumps(evals, indent=1))
            print(f"iteration {trainer.iteration}: train {trainer.history[-1]['success_rate']:.2f}, "
                  f"deterministic {e['success_rate']:.2f}", flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
