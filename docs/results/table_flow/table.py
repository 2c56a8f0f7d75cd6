"""Table I with the learned flow (docs/results/table_flow): the combined table and figure of rows A, B, C.

    python docs/results/table_flow/table.py [RUNS_BASE]

RUNS_BASE holds A/, B/, C/ in the layout of ``learner_node.analysis.report`` (``<row>/peg/<policy>-sigma<s>-seed<n>/``
with config.json, metrics.json, episodes.jsonl, evaluation.json, freespace.json); default: runs/table_flow, where
run_all.sh writes them. The numbers are report's own (``collect_runs``, ``group_stats``);
this only puts the three rows side by side. Writes table.md, table.json and table_flow_curves.png here.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from learner_node.analysis.report import _pm, collect_runs, format_iterations, group_stats

HERE = Path(__file__).resolve().parent
ROWS = {
    "A": "NF-PPO, parameter exploration, flow + S, D learned (ours)",
    "B": "NF-PPO, action noise, flow + S, D learned (paper's scheme)",
    "C": "PPO (MLP), action noise",
}


def _explore(row: str, cfg: dict) -> str:
    if row == "A":
        return f"params: ln S, ln D std {cfg['param_sigma_gains']:g}, flow std {cfg['param_sigma_flow']:g}"
    return f"action noise std {cfg['sigma_init']:g} N"


def main(base: Path) -> None:
    lines = ["| row | sigma_init (N) | exploration | iterations to 90 % (median; per seed) "
             "| state distance, first 10 it. (m) | torque, first 10 it. (Nm) | success, it. 1-5 (per seed) "
             "| success, last 5 it. (per seed) | deterministic held-out after 30 it. (per seed, of 10) "
             "| free-space converged: it. 0 / final |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    data: dict[str, dict] = {}
    curves: dict[str, dict[float, np.ndarray]] = {}
    for row in ROWS:
        runs = collect_runs(base / row)
        groups: dict[float, list] = {}
        for r in runs:
            groups.setdefault(r.sigma, []).append(r)
        curves[row] = {}
        for sigma in sorted(groups):
            group = sorted(groups[sigma], key=lambda r: r.seed)
            st = group_stats(group)
            data[f"{row}/{sigma:g}"] = st
            n = min(st["iterations"])
            per_seed = ", ".join(format_iterations(v, k) for v, k in zip(st["iterations_to_90"], st["iterations"],
                                                                        strict=True))
            evals = ", ".join(f"{round(e['success_rate'] * e['episodes'])}" for e in
                              (r.evaluation for r in group) if e) or "n/a"
            fs0, fs1 = st["freespace_initial"], st["freespace_final"]
            fs = f"{fs0[0]}/{fs0[1]} / {fs1[0]}/{fs1[1]}" if fs0[1] else "n/a"
            seeds = "" if len(group) == 3 else f" ({len(group)} seeds: {', '.join(str(s) for s in st['seeds'])})"
            lines.append(
                f"| {row} | {sigma:g}{seeds} | {_explore(row, group[0].config)} "
                f"| {format_iterations(st['median_iterations_to_90'], n)} ({per_seed}) "
                f"| {_pm(st['distance_first10'], digits=3)} | {_pm(st['torque_first10'])} "
                f"| {', '.join(f'{v:.2f}' for v in st['success_first5'])} "
                f"| {', '.join(f'{v:.2f}' for v in st['success_last5'])} | {evals} | {fs} |")
            curves[row][sigma] = np.array([[h["success_rate"] for h in r.history[:n]] for r in group])
    (HERE / "table.md").write_text("\n".join(lines) + "\n")
    (HERE / "table.json").write_text(json.dumps(data, indent=1, default=str))
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), sharey=True)
    for ax, (row, title) in zip(axes, ROWS.items(), strict=True):
        for sigma, s in curves[row].items():
            it = np.arange(1, s.shape[1] + 1)
            line, = ax.plot(it, s.mean(0), label=f"σ_init={sigma:g} ({s.shape[0]} seeds)")
            ax.fill_between(it, s.min(0), s.max(0), color=line.get_color(), alpha=0.12)
        ax.axhline(0.9, color="k", lw=0.6, ls=":")
        ax.set_title(f"{row}: {title}", fontsize=9)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
        if curves[row]:
            ax.legend(fontsize=8, loc="lower right")
    axes[0].set_ylabel("training success rate (mean over seeds; band min-max)")
    fig.suptitle("peg from the failing prior (S = 300 I N/m, D = 40 I N s/m, identity flow; deterministic 0/10)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(HERE / "table_flow_curves.png", dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parents[2] / "runs" / "table_flow")
