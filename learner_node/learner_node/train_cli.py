"""``train``: NF-PPO (or MLP-PPO) in process on one task, with metrics, checkpoints and resume.

Settings: defaults < ``--config`` (a task's ROS 2 parameters YAML) < the flags below < ``--set``.
If ``OUT/checkpoint.pt`` exists the run resumes from it (raise ``--iterations`` to extend a run);
``--fresh`` starts over instead. ``--init-checkpoint PATH`` (the setting ``init_checkpoint``) starts a
new run from another run's policy, with this run's goal (``TrainConfig.init_checkpoint``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .config import TASKS, TrainConfig, parse_sets, read_yaml_params
from .trainer import CHECKPOINT, Trainer, run_evaluations


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="train", description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, help="ROS 2 parameters YAML of the task (e.g. config/gear.yaml)")
    ap.add_argument("--task", help=f"a built-in task ({', '.join(TASKS)}) or the path of a task file")
    ap.add_argument("--policy", choices=("nf", "mlp"))
    ap.add_argument("--sigma-init", type=float, help="initial noise std, N")
    ap.add_argument("--seed", type=int)
    ap.add_argument("--iterations", type=int)
    ap.add_argument("--out", type=Path, required=True, help="output directory (metrics, checkpoint, evaluation)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="any other TrainConfig setting, e.g. --set rollouts_per_iter=8 (repeatable)")
    ap.add_argument("--init-checkpoint", type=Path, metavar="PATH",
                    help="start a new run from another run's checkpoint.pt: its flow, S, D and exploration spread, "
                         "with this run's goal and a fresh iteration count (an existing OUT/checkpoint.pt resumes "
                         "instead)")
    ap.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint in --out and start over")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--no-eval", action="store_true", help="skip the evaluations (the prior's and the final)")
    ap.add_argument("--no-prior-eval", action="store_true",
                    help="skip the prior's evaluation before iteration 1 (on the final evaluation's held-out starts)")
    ap.add_argument("-v", "--verbose", action="store_true", help="log every iteration's metrics")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 ok, 2 bad settings)."""
    ap = _parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if args.verbose:  # ours only: matplotlib's font search alone would print hundreds of DEBUG lines
        logging.getLogger("learner_node").setLevel(logging.DEBUG)
    overrides: dict[str, object] = {}
    for flag, key in (("task", "task"), ("policy", "policy"), ("sigma_init", "sigma_init"), ("seed", "seed"),
                      ("iterations", "iterations"), ("init_checkpoint", "init_checkpoint")):
        value = getattr(args, flag)
        if value is not None:
            overrides[key] = str(value) if isinstance(value, Path) else value
    try:
        overrides.update(parse_sets(args.sets))
    except ValueError as exc:
        ap.error(str(exc))
    try:
        if args.config is not None and "task" in overrides:
            yaml_task = read_yaml_params(args.config).get("task")
            if yaml_task not in (None, overrides["task"]):
                logging.warning("--task %s overrides task %s of %s: its task-specific values still apply",
                                overrides["task"], yaml_task, args.config)
        cfg = TrainConfig.from_sources(args.config, overrides)
        trainer = Trainer(cfg, args.out, progress=not args.no_progress)
        resuming = (args.out / CHECKPOINT).exists() and not args.fresh
        try:
            note = trainer.resume_or_init(fresh=args.fresh)
        except ValueError as exc:
            raise ValueError(f"{exc}; use --fresh or another --out" if resuming else str(exc)) from None
        if note:
            logging.info("%s", note)
    except ValueError as exc:
        print(f"train: error: {exc}", file=sys.stderr)
        return 2
    trainer.run(evaluate=not args.no_eval, evaluate_prior=not args.no_prior_eval)
    if trainer.history:
        from .analysis.plots import evaluation_points, plot_learning_curves

        title = f"{cfg.policy}-PPO on {cfg.task}, sigma_init {cfg.sigma_init:g}, seed {cfg.seed}"
        path = plot_learning_curves([trainer.history], args.out / "learning_curves.png", title, label="this run",
                                    evaluations=evaluation_points(run_evaluations(args.out)))
        logging.info("learning curves: %s", path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
