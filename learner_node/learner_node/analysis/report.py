"""``nf_report``: a resumable sweep of training runs and the results page (Table I of the paper).

For every combination of ``--tasks`` x ``--policies`` x ``--sigmas`` x ``--seeds`` it trains one run
in process (settings: ``config/<task>.yaml`` < the sweep's values < ``--set``) in
``RUNS/<task>/<policy>-sigma<s>-seed<n>/``, one run at a time. A run that already reached
``--iterations`` with its evaluation done is skipped; an unfinished one resumes from its checkpoint.
Each run also records every episode's final distance, torque and success (``episodes.jsonl``) and,
for the flow controller on the arm tasks, a free-space check of the deterministic controller at
iteration 0 and at the end (``freespace.json``: without contact it must converge to x_ref).

Then it collects *every* run under RUNS (also from earlier invocations) into ``RESULTS/README.md``
(the table, which runs exist, the commands) and PNG figures in RESULTS. ``--collect-only`` skips
training. Metrics (per task, policy, sigma_init, over seeds):

- iterations to 90 %: the first iteration i with mean training success over iterations i-4..i >= 0.9
  (a 5-iteration window; stochastic policy, 15 rollouts per iteration); median over seeds, a seed
  that never gets there counts as infinite;
- state distance and torque over the first 10 iterations: final distance of the TCP to the goal and
  the mean |tau - g| per episode, mean ± std over all episodes of iterations 1-10 of all seeds.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import TrainConfig
from ..rollout import EpisodeRecord
from ..trainer import CHECKPOINT, EVAL_SEED_BASE, EVALUATION_FILE, Trainer, build_policy, make_evaluator

LOG = logging.getLogger("nf_report")
EPISODES_FILE = "episodes.jsonl"
FREESPACE_FILE = "freespace.json"
SUCCESS_TARGET = 0.9
WINDOW = 5
FIRST_ITERATIONS = 10
FREESPACE_SECONDS = 10.0
FREESPACE_STARTS = 5
FREESPACE_TOLERANCE = 0.005  # m from x_ref ...
FREESPACE_SPEED = 0.005  # m/s ... and this slow at the end counts as converged
POLICY_NAMES = {"nf": "NF-PPO", "mlp": "PPO (MLP)"}


# ---------------------------------------------------------------------- metrics
def iterations_to_success(success: Sequence[float], target: float = SUCCESS_TARGET, window: int = WINDOW) -> float:
    """First iteration (1-based) whose trailing ``window``-iteration mean success is >= ``target``;
    ``inf`` if none. ``success[k]`` is the success rate of iteration k + 1."""
    s = np.asarray(success, dtype=float)
    for i in range(window, len(s) + 1):
        if s[i - window:i].mean() >= target - 1e-12:
            return float(i)
    return math.inf


def median_iterations(values: Sequence[float]) -> float:
    """Median over seeds (``inf`` for seeds that never got there; inf if at least half did not)."""
    v = np.sort(np.asarray(values, dtype=float))
    if v.size == 0:
        return math.nan
    n = v.size
    return float(v[n // 2]) if n % 2 else float(0.5 * (v[n // 2 - 1] + v[n // 2]))


def format_iterations(value: float, limit: int) -> str:
    """'37', '> 40' (never within ``limit`` iterations) or 'n/a'."""
    if math.isnan(value):
        return "n/a"
    if math.isinf(value):
        return f"> {limit}"
    return f"{value:g}"


# ---------------------------------------------------------------------- one run
@dataclass(frozen=True)
class RunSpec:
    """One training run of the sweep."""

    task: str
    policy: str
    sigma: float
    seed: int

    @property
    def name(self) -> str:
        """Folder name under ``RUNS/<task>/``."""
        return f"{self.policy}-sigma{self.sigma:g}-seed{self.seed}"


class RecordingTrainer(Trainer):
    """``Trainer`` that also appends each iteration's per-episode numbers to ``episodes.jsonl``."""

    def update(self, episodes: list[EpisodeRecord], rollout_seconds: float) -> dict[str, float]:
        """``Trainer.update`` plus one JSON line: final distances, torques, successes, max depths."""
        row = super().update(episodes, rollout_seconds)
        if self.out_dir is not None:
            line = {"iteration": self.iteration,
                    "final_distance": [e.final_distance for e in episodes],
                    "torque_norm": [e.torque_norm for e in episodes],
                    "success": [e.final_success for e in episodes],
                    "max_depth": [float(e.depth.max()) for e in episodes]}
            with (self.out_dir / EPISODES_FILE).open("a") as fh:
                fh.write(json.dumps(line) + "\n")
        return row


def read_episode_log(run_dir: Path, up_to: int | None = None) -> list[dict[str, Any]]:
    """The per-iteration lines of ``episodes.jsonl`` (the last line per iteration, up to ``up_to``)."""
    path = run_dir / EPISODES_FILE
    if not path.exists():
        return []
    by_iter: dict[int, dict[str, Any]] = {}
    for text in path.read_text().splitlines():
        if text.strip():
            line = json.loads(text)
            by_iter[int(line["iteration"])] = line
    return [by_iter[k] for k in sorted(by_iter) if up_to is None or k <= up_to]


def _truncate_episode_log(run_dir: Path, iteration: int) -> None:
    """Drop lines past ``iteration`` (written after the checkpoint a resume starts from)."""
    lines = read_episode_log(run_dir, iteration)
    path = run_dir / EPISODES_FILE
    if path.exists():
        path.write_text("".join(json.dumps(line) + "\n" for line in lines))


def freespace_check(cfg: TrainConfig, policy: object, seconds: float = FREESPACE_SECONDS,
                    starts: int = FREESPACE_STARTS) -> dict[str, Any]:
    """The deterministic controller of ``policy`` on the Panda in the free scene (no fixture) from
    ``starts`` held-out random starts for ``seconds``: final distance to x_ref, speed, converged flag."""
    from nf_controller_node.arm_model import ArmModel
    from nf_controller_node.controller import FlowController
    from nf_core import panda_spec
    from sim_bridge_node.env import InsertionEnv

    env = InsertionEnv("free")
    arm = ArmModel(part=panda_spec.GEAR_PART)  # the free scene's hand holds the gear
    ctrl = FlowController(arm, make_evaluator(policy))
    x_ref = policy.x_ref.detach().numpy().copy()
    out = []
    for k in range(starts):
        env.reset(seed=EVAL_SEED_BASE + k)
        ctrl.reset_rate_limit()
        ctrl.clear_fault()
        for _ in range(round(seconds / 1e-3)):
            env.step(ctrl.step(env.q, env.dq))
        dist = float(np.linalg.norm(env.x - x_ref))
        speed = float(np.linalg.norm(env.xdot))
        out.append({"start_seed": EVAL_SEED_BASE + k, "final_distance": dist, "final_speed": speed,
                    "fault": ctrl.fault, "converged": bool(dist < FREESPACE_TOLERANCE and speed < FREESPACE_SPEED
                                                           and not ctrl.fault)})
    return {"seconds": seconds, "tolerance_m": FREESPACE_TOLERANCE, "speed_mps": FREESPACE_SPEED,
            "converged": sum(r["converged"] for r in out), "episodes": len(out), "per_start": out}


def run_settings(spec: RunSpec, iterations: int, config_dir: Path, sets: dict[str, str]) -> TrainConfig:
    """The run's TrainConfig: ``config_dir/<task>.yaml`` < the sweep's values < ``sets``."""
    overrides: dict[str, Any] = {"policy": spec.policy, "sigma_init": spec.sigma, "seed": spec.seed,
                                 "iterations": iterations}
    overrides.update(sets)
    return TrainConfig.from_sources(config_dir / f"{spec.task}.yaml", overrides)


def is_finished(run_dir: Path, iterations: int) -> bool:
    """True when the run has ``iterations`` iterations, its evaluation and (if due) its free-space check."""
    metrics, evaluation = run_dir / "metrics.json", run_dir / EVALUATION_FILE
    if not (metrics.exists() and evaluation.exists()):
        return False
    if len(json.loads(metrics.read_text())) < iterations:
        return False
    if json.loads(evaluation.read_text()).get("iteration", -1) < iterations:
        return False
    cfg = json.loads((run_dir / "config.json").read_text())
    return not _wants_freespace(cfg) or (run_dir / FREESPACE_FILE).exists()


def _wants_freespace(cfg: dict[str, Any]) -> bool:
    return cfg.get("policy") == "nf" and cfg.get("task") in ("gear", "peg")


def train_run(spec: RunSpec, run_dir: Path, iterations: int, config_dir: Path, sets: dict[str, str],
              progress: bool = False) -> str:
    """Train (or resume, or skip) one run; returns 'skipped', 'trained' or 'error: ...'."""
    if is_finished(run_dir, iterations):
        return "skipped"
    try:
        cfg = run_settings(spec, iterations, config_dir, sets)
    except ValueError as exc:
        return f"error: {exc}"
    trainer = RecordingTrainer(cfg, run_dir, progress=progress)
    ckpt = run_dir / CHECKPOINT
    if ckpt.exists():
        try:
            trainer.load_checkpoint(ckpt)
        except ValueError as exc:
            return f"error: cannot resume from {ckpt}: {exc}"
    _truncate_episode_log(run_dir, trainer.iteration) if ckpt.exists() else (run_dir / EPISODES_FILE).unlink(
        missing_ok=True)
    trainer.run(evaluate=True)
    if _wants_freespace(cfg.to_dict()):
        initial = build_policy(cfg, trainer.x_ref)  # the same initialisation as the run's iteration 0
        result = {"initial": freespace_check(cfg, initial), "final": freespace_check(cfg, trainer.policy),
                  "iteration": trainer.iteration}
        (run_dir / FREESPACE_FILE).write_text(json.dumps(result, indent=1))
    return "trained"


# ---------------------------------------------------------------------- collecting
@dataclass
class RunResult:
    """What the report needs from one finished (or partial) run folder."""

    task: str
    policy: str
    sigma: float
    seed: int
    path: Path
    config: dict[str, Any]
    history: list[dict[str, float]]
    episodes: list[dict[str, Any]]
    evaluation: dict[str, Any] | None
    freespace: dict[str, Any] | None


def collect_runs(runs_dir: Path) -> list[RunResult]:
    """Every run folder under ``runs_dir`` (``<task>/<name>/`` with config.json and metrics.json)."""
    out = []
    for cfg_path in sorted(runs_dir.glob("*/*/config.json")):
        run_dir = cfg_path.parent
        if not (run_dir / "metrics.json").exists():
            continue
        cfg = json.loads(cfg_path.read_text())
        history = json.loads((run_dir / "metrics.json").read_text())
        ev = run_dir / EVALUATION_FILE
        fs = run_dir / FREESPACE_FILE
        out.append(RunResult(cfg["task"], cfg["policy"], float(cfg["sigma_init"]), int(cfg["seed"]), run_dir, cfg,
                             history, read_episode_log(run_dir, len(history)),
                             json.loads(ev.read_text()) if ev.exists() else None,
                             json.loads(fs.read_text()) if fs.exists() else None))
    return out


def group_stats(runs: list[RunResult]) -> dict[str, Any]:
    """Table I numbers of one (task, policy, sigma) group over its seeds."""
    its = [iterations_to_success([r["success_rate"] for r in run.history]) for run in runs]
    dist, torque = [], []
    for run in runs:
        if run.episodes:
            for line in run.episodes[:FIRST_ITERATIONS]:
                dist += line["final_distance"]
                torque += line["torque_norm"]
        else:  # plain train runs: per-iteration means only
            dist += [r["final_distance_mean"] for r in run.history[:FIRST_ITERATIONS]]
            torque += [r["torque_norm_mean"] for r in run.history[:FIRST_ITERATIONS]]
    evals = [run.evaluation for run in runs if run.evaluation]
    fs_init = [run.freespace["initial"] for run in runs if run.freespace]
    fs_final = [run.freespace["final"] for run in runs if run.freespace]
    last5 = [float(np.mean([r["success_rate"] for r in run.history[-WINDOW:]])) for run in runs]
    first5 = [float(np.mean([r["success_rate"] for r in run.history[:WINDOW]])) for run in runs]
    return {
        "seeds": sorted(run.seed for run in runs),
        "iterations": [len(run.history) for run in runs],
        "iterations_to_90": its,
        "median_iterations_to_90": median_iterations(its),
        "distance_first10": (float(np.mean(dist)), float(np.std(dist))) if dist else (math.nan, math.nan),
        "torque_first10": (float(np.mean(torque)), float(np.std(torque))) if torque else (math.nan, math.nan),
        "success_first5": first5,
        "success_last5": last5,
        "eval_success": [e["success_rate"] for e in evals],
        "eval_episodes": sum(int(e["episodes"]) for e in evals),
        "freespace_initial": (sum(f["converged"] for f in fs_init), sum(f["episodes"] for f in fs_init)),
        "freespace_final": (sum(f["converged"] for f in fs_final), sum(f["episodes"] for f in fs_final)),
    }


def _groups(runs: list[RunResult]) -> dict[tuple[str, str, float], list[RunResult]]:
    groups: dict[tuple[str, str, float], list[RunResult]] = {}
    for run in runs:
        groups.setdefault((run.task, run.policy, run.sigma), []).append(run)
    return dict(sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] != "nf", kv[0][2])))


def _pm(pair: tuple[float, float], scale: float = 1.0, digits: int = 2) -> str:
    if math.isnan(pair[0]):
        return "n/a"
    return f"{pair[0] * scale:.{digits}f} ± {pair[1] * scale:.{digits}f}"


def results_table(runs: list[RunResult]) -> tuple[str, dict[str, Any]]:
    """Markdown Table I over all groups, and the numbers as a dict (for results.json)."""
    lines = ["| task | policy | sigma_init (N) | seeds | iterations run | iterations to 90 % (median; per seed) "
             "| state distance, first 10 it. (m) | torque, first 10 it. (Nm; block N) | success, it. 1-5 (per seed) "
             "| success, last 5 it. (per seed) "
             "| held-out eval success | free-space converged: it. 0 / final |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    data: dict[str, Any] = {}
    for (task, policy, sigma), group in _groups(runs).items():
        st = group_stats(group)
        data[f"{task}/{policy}/{sigma:g}"] = st
        limit = min(st["iterations"])
        per_seed = ", ".join(format_iterations(v, n) for v, n in zip(st["iterations_to_90"], st["iterations"],
                                                                    strict=True))
        its = f"{format_iterations(st['median_iterations_to_90'], limit)} ({per_seed})"
        fs0, fs1 = st["freespace_initial"], st["freespace_final"]
        fs = f"{fs0[0]}/{fs0[1]} / {fs1[0]}/{fs1[1]}" if fs0[1] else "n/a"
        ev = ", ".join(f"{v:.2f}" for v in st["eval_success"]) or "n/a"
        lines.append(
            f"| {task} | {POLICY_NAMES.get(policy, policy)} | {sigma:g} | {len(group)} | "
            f"{', '.join(str(n) for n in st['iterations'])} | {its} | {_pm(st['distance_first10'], digits=3)} | "
            f"{_pm(st['torque_first10'])} | {', '.join(f'{v:.2f}' for v in st['success_first5'])} | "
            f"{', '.join(f'{v:.2f}' for v in st['success_last5'])} | {ev} | {fs} |"
        )
    return "\n".join(lines), data


def write_figures(runs: list[RunResult], out_dir: Path, config_dir: Path) -> list[Path]:
    """Learning curves per task, final-distance distributions (first 10 iterations, NF vs MLP) and,
    for the block task, the energy landscape before and after learning."""
    from .plots import plot_final_distance_distribution, plot_learning_curve_groups

    paths: list[Path] = []
    for task in sorted({r.task for r in runs}):
        mine = [r for r in runs if r.task == task]
        groups = {f"{POLICY_NAMES[p]} σ={s:g}": [r.history for r in g]
                  for (_, p, s), g in _groups(mine).items()}
        paths.append(plot_learning_curve_groups(groups, out_dir / f"{task}_learning_curves.png",
                                                f"{task}: mean over seeds (band: min-max)"))
        dists: dict[str, list[float]] = {}
        for (_, p, s), g in _groups(mine).items():
            values = [d for r in g for line in r.episodes[:FIRST_ITERATIONS] for d in line["final_distance"]]
            if values:
                dists[f"{POLICY_NAMES[p]} σ={s:g}"] = values
        if dists:
            paths.append(plot_final_distance_distribution(
                dists, out_dir / f"{task}_final_distance_first10.png",
                f"{task}: final distance to goal, training episodes of iterations 1-{FIRST_ITERATIONS}"))
    block = sorted((r for r in runs if r.task == "block" and r.policy == "nf" and (r.path / CHECKPOINT).exists()),
                   key=lambda r: (r.sigma, r.seed))
    if block:
        paths.append(block_landscape(block[0].path, out_dir / "block_energy_landscape.png"))
    return paths


def block_landscape(run_dir: Path, path: Path) -> Path:
    """Energy landscape of a block NF run: its iteration-0 and final controllers with a deterministic
    rollout from the first held-out start."""
    import torch

    from sim_bridge_node import scenes

    from ..rollout import RolloutRunner
    from .plots import plot_energy_landscape

    state = torch.load(run_dir / CHECKPOINT, weights_only=True)
    cfg = TrainConfig(**TrainConfig.with_defaults(state["config"]))
    trainer = Trainer(cfg)
    trainer.load_state_dict(state)
    initial = build_policy(cfg, trainer.x_ref)
    runner = RolloutRunner(cfg)
    policies = {"iteration 0": initial, f"iteration {trainer.iteration}": trainer.policy}
    trajs = {}
    for label, pol in policies.items():
        rec = runner.run_episode(make_evaluator(pol), None, EVAL_SEED_BASE, None)
        trajs[label] = rec.x
        LOG.info("block landscape %s: final distance %.4f m, success %s", label, rec.final_distance,
                 rec.final_success)
    w = 0.5 * scenes.SLOT_WIDTH
    bottom = scenes.SLOT_TOP - scenes.SLOT_DEPTH
    far = 0.6
    obstacles = [np.array([[-far, bottom], [-w, bottom], [-w, scenes.SLOT_TOP], [-far, scenes.SLOT_TOP]]),
                 np.array([[w, bottom], [far, bottom], [far, scenes.SLOT_TOP], [w, scenes.SLOT_TOP]]),
                 np.array([[-far, bottom - 0.05], [far, bottom - 0.05], [far, bottom], [-far, bottom]])]
    return plot_energy_landscape(policies, trajs, path, x_ref=trainer.x_ref, extent=(-0.25, 0.35, 0.0, 0.55),
                                 obstacles=obstacles,
                                 title=f"block, NF-PPO σ={cfg.sigma_init:g}, seed {cfg.seed} "
                                       "(walls drawn at their physical place; the TCP is the block's bottom centre)")


def write_readme(runs: list[RunResult], out_dir: Path, commands: list[str], figures: list[Path],
                 notes: str = "") -> Path:
    """``out_dir/README.md``: the table, the runs that exist, the figures and the commands; ``results.json``."""
    table, data = results_table(runs)
    listing = "\n".join(
        f"- `{r.task}/{r.path.name}`: {len(r.history)} iterations"
        f"{', evaluated' if r.evaluation else ''}{', free-space check' if r.freespace else ''}"
        for r in sorted(runs, key=lambda r: (r.task, r.policy, r.sigma, r.seed))
    )
    settings = sorted({(r.task, json.dumps({k: TrainConfig.with_defaults(r.config)[k] for k in _SHOWN})) for r in runs})
    settings_md = "\n".join(f"- {task}: `{s}`" for task, s in settings)
    figs = "\n".join(f"![{p.stem}]({p.name})" for p in figures)
    text = f"""# Learning results

Generated by `learner_node.analysis.report` ({time.strftime('%Y-%m-%d %H:%M')}). Only the runs listed below
exist; everything in the table is computed from them.

## Table I

{table}

- *iterations to 90 %*: first iteration whose 5-iteration trailing mean of the training success rate
  (stochastic policy, all rollouts of the iteration) is >= 0.9; median over seeds; `> N`: not within
  the N iterations run.
- *state distance / torque*: per training episode, the TCP's final distance to the goal and the mean
  |tau - g(q)| over its milliseconds (block: force norm in N); mean ± std over all episodes of
  iterations 1-10 of all seeds of the group.
- *held-out eval*: deterministic controller after the last iteration from held-out random starts.
- *free-space converged*: the deterministic flow controller in the free scene (no fixture) for
  {FREESPACE_SECONDS:g} s from {FREESPACE_STARTS} held-out random starts, converged = within
  {FREESPACE_TOLERANCE * 1e3:g} mm of x_ref and slower than {FREESPACE_SPEED * 1e3:g} mm/s; at iteration 0
  and after training, summed over seeds.

{notes}

## Settings of the runs

{settings_md}

## Runs

{listing}

## Figures

{figs}

## Commands

```bash
{chr(10).join(commands)}
```
"""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "README.md").write_text(text)
    (out_dir / "results.json").write_text(json.dumps(data, indent=1, default=str))
    return out_dir / "README.md"


_SHOWN = ("n_flow", "n_hidden", "flow_init", "stiffness", "stiffness_axial", "damping",
          "episode_seconds", "decision_period", "rollouts_per_iter", "learning_rate", "start", "gains",
          "exploration", "param_sigma_gains", "param_lr", "param_sigma_lr", "param_sigma_decay")


# ---------------------------------------------------------------------- CLI
def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="nf_report", description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="gear,peg,block", help="comma-separated tasks (gear, peg, block)")
    ap.add_argument("--policies", default="nf,mlp", help="comma-separated policies (nf, mlp)")
    ap.add_argument("--sigmas", default="1,1.5,2,3", help="comma-separated sigma_init values, N")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    ap.add_argument("--iterations", type=int, default=40, help="PPO iterations per run")
    ap.add_argument("--config-dir", type=Path, default=Path("config"), help="folder of <task>.yaml")
    ap.add_argument("--runs", type=Path, default=Path("runs/results"), help="run folders (checkpoints, metrics)")
    ap.add_argument("--out", type=Path, default=Path("docs/results"), help="results folder (README.md, PNGs)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="TrainConfig setting for every run of this invocation (repeatable)")
    ap.add_argument("--collect-only", action="store_true", help="no training: only rebuild the results page")
    ap.add_argument("--notes", type=Path, help="markdown file inserted into the README below the table")
    ap.add_argument("--progress", action="store_true", help="progress bar per run")
    return ap


def _split(text: str, kind: type) -> list:
    return [kind(v) for v in text.split(",") if v.strip()]


def main(argv: list[str] | None = None) -> int:
    """Entry point: train the missing runs of the sweep, then write the results page."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    sets = {}
    for item in args.sets:
        key, sep, value = item.partition("=")
        if not sep:
            print(f"nf_report: error: --set expects KEY=VALUE, got {item!r}", file=sys.stderr)
            return 2
        sets[key.strip()] = value.strip()
    specs = [RunSpec(t, p, s, n) for t in _split(args.tasks, str) for p in _split(args.policies, str)
             for s in _split(args.sigmas, float) for n in _split(args.seeds, int)]
    status: dict[str, str] = {}
    if not args.collect_only:
        for spec in specs:
            run_dir = args.runs / spec.task / spec.name
            t0 = time.perf_counter()
            status[f"{spec.task}/{spec.name}"] = result = train_run(spec, run_dir, args.iterations, args.config_dir,
                                                                   sets, args.progress)
            LOG.info("%s/%s: %s (%.0f s)", spec.task, spec.name, result, time.perf_counter() - t0)
    runs = collect_runs(args.runs)
    figures = write_figures(runs, args.out, args.config_dir) if runs else []
    log_path = args.out / "commands.txt"
    args.out.mkdir(parents=True, exist_ok=True)
    command = "python -m learner_node.analysis.report " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    previous = log_path.read_text().splitlines() if log_path.exists() else []
    if not args.collect_only and command not in previous:
        previous.append(command)
        log_path.write_text("\n".join(previous) + "\n")
    notes = args.notes.read_text() if args.notes else ""
    write_readme(runs, args.out, previous or [command], figures, notes)
    errors = {k: v for k, v in status.items() if v.startswith("error")}
    for k, v in errors.items():
        print(f"nf_report: {k}: {v}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
