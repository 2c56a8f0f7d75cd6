"""Learning-results tooling: plots write PNGs, the sweep skips finished runs, iterations to 90 %."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from learner_node.analysis import report
from learner_node.analysis.plots import plot_final_distance_distribution, plot_learning_curves

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _history(success: list[float]) -> list[dict[str, float]]:
    return [{"iteration": float(i + 1), "return_mean": -100.0 + 10 * s, "success_rate": s,
             "final_distance_mean": 0.1 * (1 - s)} for i, s in enumerate(success)]


def _is_png(path) -> bool:
    import matplotlib.image

    data = path.read_bytes()
    return data[:8] == PNG_SIGNATURE and matplotlib.image.imread(path).ndim == 3


def test_iterations_to_success_window() -> None:
    s = [0.0, 0.2, 0.9, 1.0, 0.8, 1.0, 0.9, 1.0, 0.9]
    # windows ending at 5: mean(0,.2,.9,1,.8)=.58; at 6: .78; at 7: .92 -> 7
    assert report.iterations_to_success(s) == 7
    assert report.iterations_to_success([1.0] * 4) == math.inf  # shorter than the window
    assert report.iterations_to_success([1.0] * 5) == 5
    assert report.iterations_to_success([0.9] * 5) == 5  # exactly 90 % counts
    assert report.median_iterations([7, math.inf, 9]) == 9
    assert report.median_iterations([7, math.inf, math.inf]) == math.inf
    assert report.format_iterations(math.inf, 40) == "> 40"


def test_plots_write_png(tmp_path) -> None:
    hists = [_history([0.0, 0.5, 1.0]), _history([0.0, 0.2, 0.6, 0.9])]
    p = plot_learning_curves(hists, tmp_path / "curves.png", "test")
    assert _is_png(p)
    q = plot_final_distance_distribution({"NF": [0.01, 0.02, 0.05], "MLP": [0.2, 0.3]}, tmp_path / "dist.png")
    assert _is_png(q)


def test_energy_landscape_png(tmp_path) -> None:
    from learner_node.analysis.plots import plot_energy_landscape
    from learner_node.config import TrainConfig
    from learner_node.trainer import build_policy

    cfg = TrainConfig(task="block")
    x_ref = np.array([0.0, 0.05])
    pols = {"a": build_policy(cfg, x_ref), "b": build_policy(TrainConfig(task="block", seed=1), x_ref)}
    traj = np.array([[0.1, 0.3], [0.05, 0.2], [0.0, 0.05]])
    p = plot_energy_landscape(pols, {"a": traj}, tmp_path / "land.png", x_ref=x_ref, extent=(-0.2, 0.2, 0.0, 0.4),
                              obstacles=[np.array([[0.03, 0.05], [0.2, 0.05], [0.2, 0.1], [0.03, 0.1]])], grid=15)
    assert _is_png(p)


@pytest.mark.timeout(120)
def test_sweep_skips_finished_runs(tmp_path) -> None:
    runs, out = tmp_path / "runs", tmp_path / "results"
    argv = ["--tasks", "block", "--policies", "nf", "--sigmas", "2", "--seeds", "0", "--iterations", "2",
            "--runs", str(runs), "--out", str(out), "--set", "rollouts_per_iter=2", "--set", "episode_seconds=0.05",
            "--set", "eval_episodes=1"]
    assert report.main(argv) == 0
    run_dir = runs / "block" / "nf-sigma2-seed0"
    assert len(json.loads((run_dir / "metrics.json").read_text())) == 2
    assert len(report.read_episode_log(run_dir)) == 2
    stamp = (run_dir / "checkpoint.pt").stat().st_mtime_ns
    spec = report.RunSpec("block", "nf", 2.0, 0)
    sets = {"rollouts_per_iter": "2", "episode_seconds": "0.05", "eval_episodes": "1"}
    assert report.train_run(spec, run_dir, 2, report.Path("config"), sets) == "skipped"
    assert (run_dir / "checkpoint.pt").stat().st_mtime_ns == stamp
    # raising the iterations resumes the same run
    assert report.train_run(spec, run_dir, 3, report.Path("config"), sets) == "trained"
    assert [line["iteration"] for line in report.read_episode_log(run_dir)] == [1, 2, 3]
    text = (out / "README.md").read_text()
    assert "| block | NF-PPO | 2 | 1 |" in text
    assert (out / "block_learning_curves.png").exists()
