"""What ``run_stack`` leaves in a run folder besides the learner's files: ``summary.md``, the learning
curves, a line about the bag, and a video of the final policy."""

from __future__ import annotations

import json
from pathlib import Path


def write_summary(run_dir: Path, config: Path, wall: float, exit_code: int | None, composed: bool = True,
                  how: str | None = None, arms: int = 0) -> Path:
    """``summary.md``: settings, learning progress, evaluation, timings and the files of the run;
    ``how``: what ran the episodes (default: the lockstep simulation, composed or not); ``arms``: how
    many namespaced arms were started (0: one arm without a namespace)."""
    learner = run_dir / "learner"
    metrics = json.loads((learner / "metrics.json").read_text()) if (learner / "metrics.json").exists() else []
    cfg = json.loads((learner / "config.json").read_text()) if (learner / "config.json").exists() else {}
    if how is None:
        how = "lockstep simulation, " + ("sim and controller composed in one process" if composed
                                         else "sim and controller as two processes")
        if arms:
            how += f", {arms} arms under /arm0 .. /arm{arms - 1}"
    lines = [f"# Run {run_dir.name}", "", f"Stack run with `{config}` over ROS 2 ({how}), "
             f"{wall / 60:.1f} min wall time, learner exit code {exit_code}.", ""]
    lines += origin_lines(learner, cfg)
    if cfg:
        lines += [f"Task **{cfg.get('task')}**, policy {cfg.get('policy')}-PPO, sigma_init {cfg.get('sigma_init')} N, "
                  f"seed {cfg.get('seed')}, {cfg.get('rollouts_per_iter')} rollouts of {cfg.get('episode_seconds')} s "
                  "per iteration.", ""]
    if metrics:
        lines += ["| iteration | return | success | final distance (m) | torque (Nm) | rollouts (s) | update (ms) |",
                  "|---|---|---|---|---|---|---|"]
        for r in metrics:
            lines.append(f"| {int(r['iteration'])} | {r['return_mean']:.1f} | {r['success_rate']:.2f} | "
                         f"{r['final_distance_mean']:.4f} | {r['torque_norm_mean']:.2f} | {r['rollout_seconds']:.1f} | "
                         f"{1e3 * r['update_seconds']:.0f} |")
        lines.append("")
    else:
        lines += ["No iteration completed.", ""]
    lines += arm_lines(learner / "arms.json", arms)
    evaluations = learner_evaluations(learner)
    if evaluations:
        lines += ["Deterministic controller on the held-out starts (no exploration):", "",
                  "| controller | starts | success | final distance (m) | return |", "|---|---|---|---|---|"]
        for label, e in evaluations:
            lines.append(f"| {label} | {e['episodes']} | {e['success_rate']:.2f} | "
                         f"{e['final_distance_mean']:.4f} | {e['return_mean']:.1f} |")
        lines.append("")
    if metrics:
        lines += ["Torque (Nm) is the mean over the episode of |tau| beyond gravity: what the controller adds to "
                  "the arm's gravity compensation (on a Franka, the robot adds gravity: the whole command). It grows "
                  "with the distance the episode starts from the goal, up to the potential's force bound "
                  "(docs/hardware.md, \"Torque figures\").", ""]
    lines += bag_lines(run_dir / "bag")
    lines += health_lines(run_dir / "bag")
    files = sorted(p.relative_to(run_dir) for p in run_dir.rglob("*") if p.is_file())
    shown = [f for f in files if not str(f).startswith(("logs/", "bag/"))]
    lines += ["Files:", ""] + [f"- `{f}`" for f in shown] \
        + (["- `bag/`"] if (run_dir / "bag").exists() else []) + ["- `logs/`", ""]
    path = run_dir / "summary.md"
    path.write_text("\n".join(lines))
    return path


def origin_lines(learner: Path, cfg: dict) -> list[str]:
    """Lines for ``summary.md`` saying which checkpoint the run started from (``init_checkpoint``, as its
    evaluations or its checkpoint record it), so a reader knows what the prior was; nothing for a run
    from its config's initial policy."""
    started = next((e["started_from"] for _, e in learner_evaluations(learner) if e.get("started_from")), None)
    if started is None and (learner / "checkpoint.pt").exists():
        import torch

        try:
            started = torch.load(learner / "checkpoint.pt", weights_only=True).get("started_from")
        except Exception as exc:  # a broken checkpoint must not hide the run's results
            return [f"`learner/checkpoint.pt` could not be read: {exc}", ""]
    if not started:
        return []
    return [f"Started from `{started['checkpoint']}` (after iteration {started['iteration']} of a "
            f"{started['task']} run, goal {started['x_ref']}): the prior is that policy, unchanged but for this "
            f"run's goal {cfg.get('goal') or '(the task default)'}. The prior's evaluation is the zero-shot result, "
            "the learned controller's the result of fine-tuning.", ""]


def arm_lines(arms_json: Path, started: int = 0) -> list[str]:
    """Lines for ``summary.md`` from the learner's ``arms.json``: how many arms ran rollouts and, per
    arm, its rollouts done and its dispatches lost with the arm, failed (or in safe hold) and late
    (each such rollout ran again elsewhere); nothing without the file."""
    if not arms_json.exists():
        return []
    try:
        per_arm: dict[str, dict[str, int]] = json.loads(arms_json.read_text()).get("arms", {})
    except (OSError, ValueError) as exc:
        return [f"`{arms_json.name}` could not be read: {exc}", ""]
    reruns = sum(c.get("lost", 0) + c.get("failed", 0) + c.get("hold", 0) for c in per_arm.values())
    lines = [f"{len(per_arm)} arm{'s' if len(per_arm) != 1 else ''} ran rollouts"
             + (f" ({started} started)" if started else "") + f"; {reruns} dispatches ran again elsewhere "
             "(`learner/arms.json` lists each).", ""]
    if started or len(per_arm) > 1:
        lines += ["| arm | rollouts | lost | failed or hold | late |", "|---|---|---|---|---|"]
        for name, c in sorted(per_arm.items()):
            failed = c.get("failed", 0) + c.get("hold", 0)
            lines.append(f"| {name} | {c.get('done', 0)} | {c.get('lost', 0)} | {failed} | {c.get('late', 0)} |")
        lines.append("")
    return lines


def learner_evaluations(learner: Path) -> list[tuple[str, dict]]:
    """(label, evaluation) of the learner's deterministic evaluations in ``learner``: the prior's
    (before iteration 1) and the learned controller's, those that exist."""
    from learner_node.trainer import run_evaluations

    return run_evaluations(learner)


def plot_curves(metrics_path: Path, out: Path, title: str) -> bool:
    """Learning curves of the run (``plots.plot_learning_curves``), with the deterministic controller
    on the held-out starts before and after training as points when the learner evaluated them
    (files beside ``metrics_path``); False when there is nothing to plot."""
    rows = json.loads(metrics_path.read_text()) if metrics_path.exists() else []
    if not rows:
        return False
    from learner_node.analysis.plots import evaluation_points, plot_learning_curves

    plot_learning_curves([rows], out, title, label="this run (training rollouts)",
                         evaluations=evaluation_points(learner_evaluations(metrics_path.parent)))
    return True


def bag_lines(bag: Path) -> list[str]:
    """Lines for ``summary.md`` about the run's bag (topics and message counts), or why there is none."""
    if not bag.exists():
        return ["No bag was recorded (`nf_bags` not importable).", ""]
    try:
        from nf_bags import bagfile

        health = bagfile.scan(bag)
    except Exception as exc:  # a broken bag must not hide the run's results
        return [f"Bag `{bag.name}/` could not be read: {exc}", ""]
    counts = ", ".join(f"{t} {n}" for t, n in sorted(health.counts.items()))
    state = "closed" if health.closed else "NOT closed (see `python -m nf_bags.info --repair`)"
    size = sum(f.stat().st_size for f in bag.glob("*.mcap")) / 1e6
    return [f"Bag `{bag.name}/` ({state}, {size:.1f} MB): {sum(health.counts.values())} messages: {counts}. "
            f"Inspect with `python -m nf_bags.info {bag}`.", ""]


# the last /diagnostics values the summary reports, per status: what was lost, refused or recovered
HEALTH_KEYS = {
    "control loop": ("deadline_misses", "faults", "bad_inputs", "policy_rejections", "states_missing",
                     "stamp_gaps", "states_before_reader"),
    "franka_driver: robot": ("exceptions", "recoveries", "late_ticks", "missed_cycles", "resets_done",
                             "resets_failed"),
    "sim_bridge: driver": ("command_timeouts", "bad_commands", "stale_commands"),
}


def health_lines(bag: Path) -> list[str]:
    """Lines for ``summary.md``: the counters of loss and faults the nodes last reported on /diagnostics
    (a status name ending in a ``HEALTH_KEYS`` key), as the bag holds them; nothing without a bag."""
    if not bag.exists():
        return []
    try:
        from nf_bags.reader import read_messages

        last: dict[str, dict[str, str]] = {}
        for d in read_messages(bag, ["/diagnostics"]):
            for status in d.msg.status:
                kind = next((k for k in HEALTH_KEYS if str(status.name).endswith(k)), None)
                if kind is not None:
                    values = {kv.key: kv.value for kv in status.values}
                    last[str(status.name)] = {k: values[k] for k in HEALTH_KEYS[kind] if k in values}
    except Exception as exc:  # a broken bag must not hide the run's results
        return [f"/diagnostics could not be read from the bag: {exc}", ""]
    if not last:
        return ["The bag holds no /diagnostics of the stack's nodes.", ""]
    lines = ["Last reported on /diagnostics (counts since each node started):", ""]
    for name, values in sorted(last.items()):
        lines.append(f"- {name}: " + ", ".join(f"{k} {v}" for k, v in values.items()))
    return lines + [""]


def final_video(run_dir: Path) -> Path | None:
    """GIF of the final deterministic policy from the first held-out start (None without a checkpoint)."""
    checkpoint = run_dir / "learner" / "checkpoint.pt"
    if not checkpoint.exists():
        return None
    import torch

    from learner_node.config import TrainConfig
    from learner_node.trainer import EVAL_SEED_BASE, Trainer

    state = torch.load(checkpoint, weights_only=True)
    cfg = TrainConfig(**TrainConfig.with_defaults(state["config"]))
    trainer = Trainer(cfg)
    trainer.load_state_dict(state)
    out = run_dir / "final_policy.gif"
    from learner_node.analysis.video import render_run_gif

    info = render_run_gif(trainer, out, EVAL_SEED_BASE)  # the first held-out start, as the evaluation runs it
    print(f"[stack] video of the final policy: {out} (depth {info['insertion_depth'] * 1e3:.1f} mm, "
          f"success {info['success']}; the evaluation's first held-out start)", flush=True)
    return out
