"""``nf_compare``: groups of finished training runs side by side, for probes that change one setting.

Each group is ``LABEL=DIR``; its runs are the folders below DIR that hold a ``metrics.json`` (as
``train`` and ``nf_report`` leave them). Writes one figure of learning curves (mean and range over
a group's runs, ``plots.plot_learning_curve_groups``) and prints a markdown table: training success
over the first and the last 5 iterations, the deterministic held-out evaluation and the largest
approx_kl of any update, per run (``--iterations N``: over the first N iterations only)::

    nf_compare --out docs/results/probes/gear_weak_prior.png "10 ms=runs/a" "50 ms=runs/b"
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

# the same 5-iteration windows as Table I
from .report import EVALUATION_FILE, WINDOW, iterations_to_success, median_iterations


@dataclass(frozen=True)
class RunSummary:
    """What the comparison table shows of one run folder."""

    name: str
    iterations: int
    success_first: float  # mean training success over the first WINDOW iterations
    success_last: float  # ... and over the last WINDOW
    eval_success: float | None  # deterministic held-out evaluation (None: not evaluated)
    max_kl: float  # largest approx_kl of any update
    window: float = math.inf  # the 90 % window: first iteration whose trailing WINDOW mean is >= 0.9 (inf: none)
    min_after: float | None = None  # lowest training success after the window (None: no window, or none after)


def run_folders(root: Path) -> list[Path]:
    """Every folder at or below ``root`` holding a ``metrics.json``, sorted by path."""
    return sorted(p.parent for p in root.rglob("metrics.json"))


def summarize(run: Path, iterations: int | None = None) -> tuple[RunSummary, list[dict]]:
    """The table row and the metrics rows of one run folder, up to ``iterations`` (all when None);
    the held-out evaluation only when it was made after the last iteration used. ``ValueError``
    when the run has no iteration."""
    rows = json.loads((run / "metrics.json").read_text())[:iterations]
    if not rows:
        raise ValueError(f"{run}: metrics.json holds no iteration")
    success = [float(r["success_rate"]) for r in rows]
    evaluation = run / EVALUATION_FILE
    eval_success = None
    if evaluation.exists():
        result = json.loads(evaluation.read_text())
        if int(result.get("iteration", -1)) == int(rows[-1]["iteration"]):
            eval_success = float(result["success_rate"])
    window = iterations_to_success(success)
    after = success[int(window):] if math.isfinite(window) else []
    summary = RunSummary(run.name, len(rows), sum(success[:WINDOW]) / len(success[:WINDOW]),
                         sum(success[-WINDOW:]) / len(success[-WINDOW:]), eval_success,
                         max(float(r.get("approx_kl", 0.0)) for r in rows), window, min(after) if after else None)
    return summary, rows


def markdown_table(groups: Mapping[str, Sequence[RunSummary]]) -> str:
    """One line per group, the per-run values in run order."""
    def each(values: Sequence[float | None], fmt: str = "{:.2f}") -> str:
        return ", ".join("-" if v is None else fmt.format(v) for v in values)

    lines = [f"| group | runs | iterations | success, it. 1-{WINDOW} | success, last {WINDOW} it. | "
             f"90 % window (median) | lowest success after it | held-out eval success | largest approx_kl |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, runs in groups.items():
        windows = [r.window if math.isfinite(r.window) else None for r in runs]
        median = median_iterations([r.window for r in runs])
        lines.append(f"| {label} | {len(runs)} | {each([r.iterations for r in runs], '{:d}')} | "
                     f"{each([r.success_first for r in runs])} | {each([r.success_last for r in runs])} | "
                     f"{each(windows, '{:.0f}')} ({'-' if not math.isfinite(median) else f'{median:.0f}'}) | "
                     f"{each([r.min_after for r in runs])} | "
                     f"{each([r.eval_success for r in runs])} | {each([r.max_kl for r in runs], '{:.3f}')} |")
    return "\n".join(lines)


def _group(text: str) -> tuple[str, Path]:
    label, sep, folder = text.partition("=")
    if not sep or not label or not folder:
        raise argparse.ArgumentTypeError(f"expected LABEL=DIR, got {text!r}")
    return label, Path(folder)


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``nf_compare``."""
    ap = argparse.ArgumentParser(prog="nf_compare", description=__doc__.splitlines()[0])
    ap.add_argument("groups", nargs="+", type=_group, metavar="LABEL=DIR", help="a group of run folders")
    ap.add_argument("--out", type=Path, required=True, help="PNG of the learning curves")
    ap.add_argument("--title", default="", help="figure title")
    ap.add_argument("--markdown", type=Path, default=None, help="also write the table to this file")
    ap.add_argument("--iterations", type=int, default=None,
                    help="use only the first N iterations of every run (equal budgets; an evaluation made "
                         "later is shown as -)")
    args = ap.parse_args(argv)
    if args.iterations is not None and args.iterations < 1:
        ap.error(f"--iterations must be >= 1, got {args.iterations}")
    summaries: dict[str, list[RunSummary]] = {}
    histories: dict[str, list[list[dict]]] = {}
    for label, root in args.groups:
        runs = run_folders(root)
        if not runs:
            ap.error(f"group {label!r}: no run folder (with metrics.json) below {root}")
        try:
            pairs = [summarize(r, args.iterations) for r in runs]
        except (ValueError, KeyError, json.JSONDecodeError) as exc:
            ap.error(f"group {label!r}: {exc}")
        summaries[label] = [s for s, _ in pairs]
        histories[label] = [rows for _, rows in pairs]
    from .plots import plot_learning_curve_groups

    plot_learning_curve_groups(histories, args.out, args.title)
    table = markdown_table(summaries)
    print(table)
    print(f"figure: {args.out}")
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
