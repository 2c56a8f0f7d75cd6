"""Fingerprints of the shipped learner configs: 2 in-process iterations each, metrics and final weights.

``python tests/fingerprint.py --write`` stores them in tests/fingerprints/<cpu>/, one folder per kind of
CPU (LLVM's name for the host: numba, MuJoCo and torch pick their code by CPU, and contact dynamics
turn the last bit of a sum into another success rate within two iterations, so numbers are only equal
on the same kind). ``test_fingerprints.py`` recomputes them and compares to 1e-9 with this CPU's, so a
refactor of the learner cannot change what the shipped configs learn without a test saying so.
``first-machine/``: written on the machine the fingerprints were first stored on, its CPU not recorded.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
FOLDER = Path(__file__).resolve().parent / "fingerprints"
ITERATIONS = 2
EVAL_EPISODES = 2
# name -> config files, layered in order (the learner's own view of each shipped run)
RUNS: dict[str, list[str]] = {
    "gear_learn": ["config/gear_learn.yaml"],
    "gear_learn_arm": ["config/gear_learn.yaml", "config/franka_learn.yaml"],
    "peg": ["config/peg.yaml"],
    "block": ["config/block.yaml"],
}


def machine() -> str:
    """This CPU's kind as LLVM names it (``znver4``, ``skylake-avx512``, ...): the fingerprints' folder."""
    try:
        import llvmlite.binding as llvm

        return str(llvm.get_host_cpu_name()) or "unknown"
    except Exception:  # no llvmlite: one folder for every CPU of this architecture
        import platform

        return platform.machine() or "unknown"


def stored(name: str) -> dict[str, Any]:
    """Every stored fingerprint of ``name``: {folder (a CPU kind): fingerprint}."""
    return {f.parent.name: json.loads(f.read_text()) for f in sorted(FOLDER.glob(f"*/{name}.json"))}


def _config(files: list[str]):
    from learner_node.config import TrainConfig

    cfg = TrainConfig.from_sources([ROOT / f for f in files],
                                   {"iterations": ITERATIONS, "eval_episodes": EVAL_EPISODES})
    return cfg


def _flat(state: Any, prefix: str = "") -> dict[str, list[float]]:
    """Every tensor / array in a (nested) state dict, as a flat list of floats."""
    import torch

    out: dict[str, list[float]] = {}
    if isinstance(state, dict):
        for k, v in state.items():
            out.update(_flat(v, f"{prefix}{k}."))
    elif isinstance(state, torch.Tensor) and state.dtype.is_floating_point:
        out[prefix[:-1]] = state.detach().double().flatten().tolist()
    elif isinstance(state, np.ndarray) and state.dtype.kind == "f":
        out[prefix[:-1]] = state.astype(float).flatten().tolist()
    return out


def compute(name: str) -> dict[str, Any]:
    """Run ``RUNS[name]`` for ``ITERATIONS`` iterations in process; its metrics, evaluation and weights."""
    import torch

    from learner_node.trainer import Trainer, metrics_without_timing

    cfg = _config(RUNS[name])
    trainer = Trainer(cfg)
    evaluation = trainer.run(evaluate=True, evaluate_prior=False)
    weights = _flat(trainer.policy.state_dict())
    if trainer.explorer is not None:
        with torch.no_grad():
            weights.update(_flat({"explorer": trainer.explorer.state_dict()}))
    return {
        "files": RUNS[name],
        "metrics": [metrics_without_timing(r) for r in trainer.history],
        "evaluation": {k: evaluation[k] for k in ("success_rate", "return_mean", "final_distance_mean")},
        "weights": weights,
    }


def differences(expected: Any, actual: Any, path: str = "", tol: float = 1e-9) -> list[str]:
    """Where two fingerprints differ by more than ``tol`` (relative to max(1, |value|))."""
    if isinstance(expected, dict):
        if not isinstance(actual, dict):
            return [f"{path}: expected a mapping"]
        out = [f"{path}.{k}: missing" for k in expected if k not in actual]
        out += [f"{path}.{k}: unexpected" for k in actual if k not in expected]
        for k in expected:
            if k in actual:
                out += differences(expected[k], actual[k], f"{path}.{k}", tol)
        return out
    if isinstance(expected, list):
        if not isinstance(actual, list) or len(actual) != len(expected):
            return [f"{path}: length {len(expected)} vs {len(actual) if isinstance(actual, list) else actual!r}"]
        out = []
        for i, (e, a) in enumerate(zip(expected, actual, strict=True)):
            out += differences(e, a, f"{path}[{i}]", tol)
        return out[:20]
    if isinstance(expected, float) or isinstance(actual, float):
        if isinstance(expected, float) and isinstance(actual, float) and math.isnan(expected) and math.isnan(actual):
            return []
        if abs(float(expected) - float(actual)) > tol * max(1.0, abs(float(expected))):
            return [f"{path}: {expected!r} vs {actual!r}"]
        return []
    return [] if expected == actual else [f"{path}: {expected!r} vs {actual!r}"]


def main(argv: list[str] | None = None) -> int:
    """Compute the fingerprints; with --write store them, else compare with the stored ones."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true")
    ap.add_argument("names", nargs="*", default=list(RUNS))
    args = ap.parse_args(argv)
    bad = 0
    for name in args.names:
        fp = compute(name)
        path = FOLDER / machine() / f"{name}.json"
        if args.write:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(fp, indent=0) + "\n")
            print(f"wrote {path}")
        else:
            diff = differences(json.loads(path.read_text()), fp)
            print(f"{name}: {'same' if not diff else 'DIFFERENT'}")
            for d in diff[:10]:
                print("  ", d)
            bad += bool(diff)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
