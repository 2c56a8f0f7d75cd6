"""What the robot path's episode torque is made of: from a run's bag, |tau| of the running controller's
commands (``controller_status``, 50 Hz) binned by the TCP's distance to the goal, and the share of the
episode spent at each distance; beside it, the pull the potential's bound allows and the joint torque
that pull takes at the start pose (Jacobian transpose, Pinocchio).

    python experiments/robot_torque.py runs/reflex20/bag [--bound 60]

Answer in docs/results/robot_reliability.md.
"""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np

BINS = (0.0, 0.005, 0.02, 0.05, 0.1, 0.15, 0.25)  # m from the goal


def episode_samples(bag: str) -> tuple[np.ndarray, np.ndarray]:
    """(distance to x_ref in m, |tau| in Nm) of every controller_status sample taken while an episode ran."""
    from nf_bags.reader import read_messages

    dist, torque = [], []
    for d in read_messages(bag, ["/controller_status"]):
        m = d.msg
        if int(m.mode) != 1 or len(m.x) != 3 or len(m.x_ref) != 3:
            continue
        dist.append(float(np.linalg.norm(np.asarray(m.x) - np.asarray(m.x_ref))))
        torque.append(float(m.torque_norm))
    return np.asarray(dist), np.asarray(torque)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bag")
    ap.add_argument("--bound", type=float, default=60.0, help="N, the policy's potential_force_bound")
    args = ap.parse_args()
    dist, torque = episode_samples(args.bag)
    if dist.size == 0:
        print("no controller_status samples of a running episode in the bag")
        return 1
    rows = []
    for lo, hi in itertools.pairwise(BINS):
        sel = (dist >= lo) & (dist < hi)
        if sel.any():
            rows.append({"distance_m": f"{lo:g}-{hi:g}", "share": round(float(sel.mean()), 3),
                         "torque_median_Nm": round(float(np.median(torque[sel])), 2),
                         "torque_p90_Nm": round(float(np.percentile(torque[sel], 90)), 2)})
    print(json.dumps({"samples": int(dist.size), "torque_mean_Nm": round(float(torque.mean()), 2),
                      "distance_median_m": round(float(np.median(dist)), 4), "bins": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
