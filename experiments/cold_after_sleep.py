"""What a thread pays for having slept: the CPU time of small calls right after a sleep.

On a VM whose idle vCPU is descheduled, a thread that wakes up runs its first instructions with
cold caches. This times (``time.thread_time``: CPU time of this thread, not waiting) a few calls
the stack's threads make, each right after a sleep of 0, 1 and 20 ms: an rclpy publish of a
``ControllerStatus`` (no subscriber), building that message, the norm of a 7-vector, and an empty
call. The controller's executor thread wakes every few ms to 20 ms (status, chunks, goals), so
its callbacks pay the 20 ms row. Writes ``experiments/results/cold_after_sleep.json``.
Usage: PYTHONPATH=bench:$PYTHONPATH python experiments/cold_after_sleep.py [--calls 200]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import sources  # noqa: F401  (the package sources first on sys.path)

from nf_bringup.processes import allocate_domain_id, isolate

HERE = Path(__file__).resolve().parent
GAPS_S = (0.0, 0.001, 0.02)


def cpu_us_after_sleep(fn: Callable[[], object], gap: float, calls: int) -> float:
    """Median CPU time (us) of ``fn`` called right after sleeping ``gap`` s."""
    spent = []
    for _ in range(calls):
        if gap:
            time.sleep(gap)
        c0 = time.thread_time()
        fn()
        spent.append(time.thread_time() - c0)
    return 1e6 * statistics.median(spent)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=200, help="calls per operation and gap")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "cold_after_sleep.json")
    args = parser.parse_args()
    isolate(os.environ, allocate_domain_id(), sources=False)  # loopback only, its own domain
    import rclpy
    from nf_msgs.msg import ControllerStatus

    rclpy.init()
    node = rclpy.create_node("cold_after_sleep")
    try:
        pub = node.create_publisher(ControllerStatus, "cold_after_sleep_status", 10)
        msg = ControllerStatus(x=[0.4, 0.0, 0.3], x_ref=[0.4, 0.0, 0.3])
        v = np.ones(7)
        ops = {"publish ControllerStatus": lambda: pub.publish(msg),
               "build ControllerStatus": lambda: ControllerStatus(x=[0.4, 0.0, 0.3], x_ref=[0.4, 0.0, 0.3]),
               "norm of a 7-vector": lambda: np.linalg.norm(v),
               "empty call": lambda: None}
        table = {name: {f"{gap * 1e3:g} ms": cpu_us_after_sleep(fn, gap, args.calls) for gap in GAPS_S}
                 for name, fn in ops.items()}
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    result = {"benchmark": "cold_after_sleep", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
              "machine": platform.machine(), "cpus": os.cpu_count(), "calls": args.calls,
              "median_cpu_us_after_sleep": table}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print("median CPU time per call (us) after a sleep of " + ", ".join(f"{g * 1e3:g} ms" for g in GAPS_S))
    for name, row in table.items():
        print(f"  {name:26s} " + "  ".join(f"{x:8.1f}" for x in row.values()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
