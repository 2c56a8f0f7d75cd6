"""``nf_compare`` on real (tiny) training runs: groups found below their folders, the table's numbers
taken from each run's own files, a figure written, and bad groups refused with a reason."""

from __future__ import annotations

import json

import pytest
import torch

from learner_node.analysis.compare import main as compare_main
from learner_node.analysis.compare import run_folders, summarize
from learner_node.config import TrainConfig
from learner_node.trainer import Trainer

TINY = {"task": "block", "iterations": 2, "rollouts_per_iter": 3, "episode_seconds": 0.2, "minibatch_size": 16,
        "update_epochs": 2, "eval_episodes": 2}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two groups: two evaluated seeds (one folder deeper, as nf_report nests them) and one unevaluated run."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("runs")
    for seed in (0, 1):
        Trainer(TrainConfig(**{**TINY, "seed": seed}), root / "a" / "block" / f"nf-seed{seed}").run()
    Trainer(TrainConfig(**{**TINY, "iterations": 1}), root / "b" / "nf-seed0").run(evaluate=False)
    torch.set_num_threads(before)
    return root


def test_table_and_figure_come_from_the_runs_files(runs, tmp_path, capsys):
    assert [p.name for p in run_folders(runs / "a")] == ["nf-seed0", "nf-seed1"]
    summary, rows = summarize(runs / "a" / "block" / "nf-seed1")
    success = [r["success_rate"] for r in rows]
    assert summary.iterations == 2 and summary.success_first == pytest.approx(sum(success) / 2)
    assert summary.max_kl == max(r["approx_kl"] for r in rows)
    window = next((i + 1 for i in range(4, len(success)) if sum(success[i - 4:i + 1]) / 5 >= 0.9), None)
    assert summary.window == (window or float("inf"))  # two iterations: no 5-iteration window yet
    evaluation = json.loads((runs / "a" / "block" / "nf-seed1" / "evaluation.json").read_text())
    assert summary.eval_success == evaluation["success_rate"]

    out, table = tmp_path / "cmp.png", tmp_path / "cmp.md"
    assert compare_main([f"two seeds={runs / 'a'}", f"unevaluated={runs / 'b'}", "--out", str(out),
                         "--markdown", str(table)]) == 0
    assert out.stat().st_size > 10_000
    lines = table.read_text().splitlines()
    assert lines[2].startswith("| two seeds | 2 | 2, 2 |") and "| -, - (-) |" in lines[2]  # no window
    assert lines[3].startswith("| unevaluated | 1 | 1 |") and "| - |" in lines[3]  # no evaluation: a dash
    assert "two seeds" in capsys.readouterr().out


def test_equal_budgets_cut_every_run_and_drop_a_later_evaluation(runs):
    full, rows = summarize(runs / "a" / "block" / "nf-seed0")
    cut, cut_rows = summarize(runs / "a" / "block" / "nf-seed0", iterations=1)
    assert full.eval_success is not None and cut.eval_success is None  # evaluated after iteration 2, not 1
    assert cut.iterations == 1 and cut_rows == rows[:1]
    assert cut.success_first == cut.success_last == rows[0]["success_rate"]


def test_the_window_and_the_lowest_success_after_it(tmp_path):
    run = tmp_path / "r"
    run.mkdir()
    success = [0.2, 0.9, 1.0, 0.9, 0.9, 0.8, 1.0, 0.7, 1.0]  # trailing 5-iteration mean 0.90 first at 6
    rows = [{"iteration": i + 1, "success_rate": s, "approx_kl": 0.1} for i, s in enumerate(success)]
    (run / "metrics.json").write_text(json.dumps(rows))
    summary, _ = summarize(run)
    assert summary.window == 6 and summary.min_after == 0.7


def test_bad_groups_are_refused_with_a_reason(runs, tmp_path, capsys):
    for argv, reason in ((["no-equals-sign"], "expected LABEL=DIR"),
                         ([f"empty={tmp_path}"], "no run folder (with metrics.json) below"),
                         ([f"a={runs / 'a'}", "--iterations", "0"], "--iterations must be >= 1")):
        with pytest.raises(SystemExit) as exc:
            compare_main([*argv, "--out", str(tmp_path / "x.png")])
        assert exc.value.code == 2
        assert reason in capsys.readouterr().err
