"""gear_clamp (issue 31, item 2): the straight path hits the clamp, and quadratic wells do not get over it.

1. Geometry: the gear (ring of outer radius GEAR_OUTER_RADIUS, GEAR_DEPTH tall above the TCP) swept
   along the straight line from each held-out start's TCP to the goal: where it first overlaps the clamp.
2. Physics: the deterministic controller with the identity flow (a single quadratic well) and a few
   diagonal S, D, from the first held-out starts: success, the highest TCP z, how far towards the shaft
   the gear got (smallest TCP x) and where it ended.

    python experiments/gear_clamp_check.py [--episodes 10]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

from learner_node.config import TrainConfig
from learner_node.trainer import EVAL_SEED_BASE, Trainer, make_evaluator
from nf_core import panda_spec
from nf_core.task_spec import load_task

TASK = load_task("gear_clamp")

CONFIG = Path(__file__).resolve().parents[1] / "config" / "gear_clamp.yaml"


def gear_overlaps_clamp(tcp: np.ndarray) -> bool:
    """Whether the gear (bounding cylinder, TCP at its lower face) at TCP ``tcp`` overlaps the clamp box."""
    r, h = panda_spec.GEAR_OUTER_RADIUS, panda_spec.GEAR_DEPTH
    lo = np.array([TASK.clamp.center_x - TASK.clamp.half_thickness, TASK.top[:2][1] - TASK.clamp.half_length,
                   0.0])
    hi = np.array([TASK.clamp.center_x + TASK.clamp.half_thickness,
                   TASK.top[:2][1] + TASK.clamp.half_length, TASK.clamp.top])
    # closest point of the box's xy rectangle to the gear axis, and the z ranges
    nearest = np.clip(tcp[:2], lo[:2], hi[:2])
    lateral = math.hypot(*(tcp[:2] - nearest)) < r
    return bool(lateral and tcp[2] < hi[2] and tcp[2] + h > lo[2])


def straight_line_hit(start: np.ndarray, goal: np.ndarray, n: int = 2001) -> float | None:
    """Fraction of the way along the straight line where the gear first overlaps the clamp (None: never)."""
    for s in np.linspace(0.0, 1.0, n):
        if gear_overlaps_clamp(start + s * (goal - start)):
            return float(s)
    return None


def run_gains(trainer: Trainer, s_diag, d_diag, seeds) -> list[dict]:
    pol = trainer.policy
    with torch.no_grad():
        pol.ln_s.copy_(torch.log(torch.as_tensor(s_diag, dtype=pol.ln_s.dtype)))
        pol.ln_d.copy_(torch.log(torch.as_tensor(d_diag, dtype=pol.ln_d.dtype)))
    pol.sync_gains()
    ev = make_evaluator(pol)
    out = []
    for seed in seeds:
        rec = trainer.runner.run_episode(ev, None, seed, None)
        x = rec.x
        out.append({"success": rec.final_success, "z_max": float(x[:, 2].max()), "x_min": float(x[:, 0].min()),
                    "final": x[-1].round(3).tolist(), "z0": float(x[0, 2]),
                    "torque": rec.torque_norm})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=10)
    args = ap.parse_args()
    cfg = TrainConfig.from_sources(CONFIG, {"eval_episodes": args.episodes})
    trainer = Trainer(cfg)
    env = trainer.runner.env
    goal = env.goal_position
    print(f"clamp: x {TASK.clamp.center_x - TASK.clamp.half_thickness:.3f}-"
          f"{TASK.clamp.center_x + TASK.clamp.half_thickness:.3f} m, |y - {TASK.top[:2][1]}| <= "
          f"{TASK.clamp.half_length} m, z 0-{TASK.clamp.top} m; goal TCP {goal.round(3).tolist()}")
    print("1. straight line start -> goal (gear's bounding cylinder), held-out starts:")
    seeds = [EVAL_SEED_BASE + k for k in range(10)]
    for seed in seeds:
        env.reset(seed=seed)
        x0 = env.x
        hit = straight_line_hit(x0, goal)
        where = "never" if hit is None else f"at {hit:.2f} of the way, TCP {(x0 + hit * (goal - x0)).round(3).tolist()}"
        print(f"   start {x0.round(3).tolist()}: hits the clamp {where}")
    print(f"2. identity flow, diagonal S (N/m), D (N s/m), deterministic, {args.episodes} held-out starts:")
    cases = [
        ("prior (gear_clamp.yaml)", [300, 300, 300], [40, 40, 40]),
        ("gear_learn's learned (lateral stiff)", [1127, 744, 135], [35, 35, 35]),
        ("z fast, lateral slow", [100, 100, 2000], [60, 60, 40]),
        ("z fast, lateral slow, underdamped", [100, 100, 2000], [20, 20, 5]),
        ("lateral fast, z slow", [2000, 2000, 50], [40, 40, 40]),
        ("lateral stiff, z very soft", [1000, 1000, 10], [40, 40, 40]),
        ("the hand-built flow's S, D", [400, 400, 135], [40, 40, 100]),
        ("stiff everywhere", [3000, 3000, 3000], [60, 60, 60]),
        ("stiff, lightly damped", [1500, 1500, 1500], [10, 10, 10]),
        ("stiff, very lightly damped", [1500, 1500, 1500], [5, 5, 5]),
        ("largest S, smallest D", [10000, 10000, 10000], [1, 1, 1]),
    ]
    for name, s_diag, d_diag in cases:
        res = run_gains(trainer, s_diag, d_diag, seeds[: args.episodes])
        ok = sum(r["success"] for r in res)
        rise = max(r["z_max"] - r["z0"] for r in res)
        print(f"   {name:40s} S={s_diag} D={d_diag}: success {ok}/{len(res)}, highest rise above the start "
              f"{rise * 1e3:.1f} mm, max TCP z {max(r['z_max'] for r in res):.3f} m, "
              f"smallest x reached {min(r['x_min'] for r in res):.3f} m, over the clamp in "
              f"{sum(r['x_min'] < TASK.clamp.center_x - TASK.clamp.half_thickness - 0.03 for r in res)}, "
              f"mean torque {np.mean([r['torque'] for r in res]):.1f} Nm")


if __name__ == "__main__":
    main()
