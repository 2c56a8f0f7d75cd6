"""How much a 1 kHz tick pays for waiting: ``ControllerHost.tick`` (the gear task's iteration-0
flow policy, an episode-free idle_mode "policy" tick) timed in a tight loop, and right after each
way a driver can wait for its next period, in interleaved blocks of one process (no ROS):

- ``tight``: back to back, nothing in between (what a profiler of the step alone sees);
- ``asleep``: after ``time.sleep`` of most of a 1 ms period;
- ``deadline_wait``: after ``DeadlineWait(0.3 ms)`` (asleep, then awake without the GIL), as the
  composed realtime sim waits with ``realtime_warm: false``;
- ``deadline_wait_warm``: the same with the controller's cache warm-up before the spin
  (``ControllerHost.warm``), as it waits by default;
- ``awake``: ``DeadlineWait`` spinning the whole period without the GIL (the thread never sleeps;
  it costs a whole core).

    PYTHONPATH=bench:$PYTHONPATH python experiments/cold_tick.py [--ticks 3000] [--blocks 4]

Writes ``experiments/results/cold_tick.json``. A probe for docs/nodes.md, not a target benchmark.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CONFIG = HERE.parent / "config" / "gear_learn.yaml"
PERIOD = 0.001


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=3000, help="ticks per block")
    parser.add_argument("--blocks", type=int, default=4, help="interleaved blocks per way of waiting")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "cold_tick.json")
    args = parser.parse_args()
    from bench_stack import gear_host

    from sim_bridge_node.deadline_wait import DeadlineWait

    _, env, host = gear_host(CONFIG, "policy")
    q, dq = env.q, env.dq
    spin = DeadlineWait(3e-4)
    awake = DeadlineWait(PERIOD)  # the whole period awake: the thread never sleeps
    perf = time.perf_counter
    stamp = [0]

    def tick() -> float:
        stamp[0] += 1_000_000
        t0 = perf()
        host.tick(stamp[0], q, dq, time.monotonic())
        return perf() - t0

    def block(way: str, n: int) -> np.ndarray:
        out = np.empty(n)
        due = perf()
        for i in range(n):
            due += PERIOD
            if way == "asleep":
                time.sleep(max(due - perf(), 0.0))
            elif way == "deadline_wait":
                spin.wait(due)
            elif way == "deadline_wait_warm":
                spin.wait(due, host.warm)
            elif way == "awake":
                awake.wait(due)
            out[i] = tick()
        return out

    ways = ("tight", "asleep", "deadline_wait", "deadline_wait_warm", "awake")
    samples: dict[str, list[np.ndarray]] = {w: [] for w in ways}
    block("tight", 500)  # compiled and warm before anything is timed
    gc.collect()
    gc.freeze()
    for b in range(args.blocks):
        for way in ways:
            samples[way].append(block(way, args.ticks))
        print(f"block {b + 1}/{args.blocks}: " + ", ".join(
            f"{w} p50 {np.median(samples[w][-1]) * 1e6:.1f} us" for w in ways), flush=True)
    result = {"benchmark": "cold_tick", "date": time.strftime("%Y-%m-%d %H:%M:%S"), "cpus": os.cpu_count(),
              "machine": platform.machine(), "load_1min": os.getloadavg()[0], "ticks_per_block": args.ticks,
              "blocks": args.blocks}
    for way in ways:
        us = np.concatenate(samples[way]) * 1e6
        result[way] = {"p50_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
                       "p999_us": float(np.percentile(us, 99.9)), "max_us": float(us.max()), "count": int(us.size)}
        print(f"{way:20s} host.tick p50 {result[way]['p50_us']:6.1f} us, p99 {result[way]['p99_us']:6.1f} us, "
              f"p99.9 {result[way]['p999_us']:6.1f} us", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
