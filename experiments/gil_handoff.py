"""What a second Python thread costs the composed lockstep loop beyond its own CPU time (the GIL).

The composed stack runs the driver loop on one thread and the ROS executor (status at 50 Hz,
feedback, diagnostics, rollout chunks, policy messages) on another, in one interpreter. MuJoCo's
``mj_step`` lets go of the GIL while it steps, so whenever the other thread wants to run Python
it gets the GIL during a step, and the driver thread, its step done, waits until it is handed back:
a wake-up across cores each time, on top of the other thread's own work. This benchmark shows both
parts with no ROS at all:

1. whether ``mj_step`` releases the GIL: a counting thread's rate while the main thread steps the
   gear scene, against its rate while the main thread sleeps;
2. what that costs: the composed driver loop alone (``bench_stack.loop_alone``: ``SimDriverLoop``
   + ``ControllerHost`` on a thread, lockstep, no publishing) with nothing else running, against the
   same with a thread that wakes every ``--period`` s and runs ``--work`` s of Python (about what the
   executor does for one status message), in alternated pairs; the loop's loss against that
   thread's CPU share.

Usage: PYTHONPATH=bench:$PYTHONPATH python experiments/gil_handoff.py [--pairs 4] [--period 0.001]
    [--work 20e-6] [--quick]
Writes experiments/results/gil_handoff.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import threading
import time
from pathlib import Path

from bench_stack import CONFIG, loop_alone

HERE = Path(__file__).resolve().parent


def mj_step_releases_gil(steps: int = 3000) -> dict:
    """A counting thread's rate while the main thread sleeps and while it runs ``mj_step``."""
    import mujoco

    from learner_node.config import TrainConfig
    from sim_bridge_node.env import InsertionEnv

    env = InsertionEnv(TrainConfig.from_sources(CONFIG, {}).task)
    count = [0]
    stop = threading.Event()

    def counter() -> None:
        while not stop.is_set():
            count[0] += 1

    thread = threading.Thread(target=counter, daemon=True)
    thread.start()
    time.sleep(0.2)
    c0, t0 = count[0], time.perf_counter()
    time.sleep(0.5)
    idle = (count[0] - c0) / (time.perf_counter() - t0)
    c0, t0 = count[0], time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(env.model, env.data)
    wall = time.perf_counter() - t0
    during = (count[0] - c0) / wall
    stop.set()
    thread.join()
    out = {"counter_rate_idle": idle, "counter_rate_during_mj_step": during, "ratio": during / idle,
           "mj_step_us_with_a_busy_python_thread": wall / steps * 1e6}
    print(f"mj_step and the GIL: a busy counting thread ran at {100 * out['ratio']:.0f} % of its idle rate while "
          f"the main thread stepped (it releases the GIL); each step then took "
          f"{out['mj_step_us_with_a_busy_python_thread']:.0f} us (waiting to get the GIL back)", flush=True)
    return out


def _waker(stop: threading.Event, period: float, work: float, cpu: list[float]) -> None:
    """Every ``period`` s: ``work`` s of Python (a busy loop), as an executor callback would."""
    c0 = time.thread_time()
    while not stop.is_set():
        time.sleep(period)
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < work:
            pass
    cpu.append(time.thread_time() - c0)


def loop_with_and_without(pairs: int, episodes: int, seconds: float, period: float, work: float) -> dict:
    """Alternated runs of the loop alone and with the waking thread: steps/s (median of each run's
    episodes) and the thread's CPU share."""
    rows = []
    for i in range(pairs):
        row = {}
        for mode in (("alone", "with_thread") if i % 2 == 0 else ("with_thread", "alone")):
            stop, cpu = threading.Event(), []
            thread = None
            if mode == "with_thread":
                thread = threading.Thread(target=_waker, args=(stop, period, work, cpu), daemon=True)
                thread.start()
            t0 = time.perf_counter()
            rates = loop_alone(episodes, seconds)
            wall = time.perf_counter() - t0
            stop.set()
            if thread is not None:
                thread.join()
                row["thread_cpu_share"] = cpu[0] / wall
            row[mode] = statistics.median(rates)
        row["loss"] = 1.0 - row["with_thread"] / row["alone"]
        rows.append(row)
        print(f"pair {i + 1}/{pairs}: loop alone {row['alone']:.0f} steps/s, with the thread {row['with_thread']:.0f} "
              f"({100 * row['loss']:.0f} % fewer; the thread used {100 * row['thread_cpu_share']:.1f} % of a core)",
              flush=True)
    return {"pairs": rows, "loss_median": statistics.median(r["loss"] for r in rows),
            "thread_cpu_share_median": statistics.median(r["thread_cpu_share"] for r in rows)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--episodes", type=int, default=4, help="episodes per run of the loop")
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per episode")
    parser.add_argument("--period", type=float, default=1e-3, help="s between the thread's wake-ups")
    parser.add_argument("--work", type=float, default=20e-6, help="s of Python per wake-up")
    parser.add_argument("--quick", action="store_true", help="2 pairs of 2 episodes of 2 s")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "gil_handoff.json")
    args = parser.parse_args()
    if args.quick:
        args.pairs, args.episodes, args.seconds = 2, 2, 2.0
    release = mj_step_releases_gil()
    loop = loop_with_and_without(args.pairs, args.episodes, args.seconds, args.period, args.work)
    print(f"median: the loop lost {100 * loop['loss_median']:.0f} % of its steps to a thread using "
          f"{100 * loop['thread_cpu_share_median']:.1f} % of a core", flush=True)
    result = {"benchmark": "GIL hand-over cost to the composed lockstep loop", "config": str(CONFIG),
              "command": "python experiments/gil_handoff.py" + (" --quick" if args.quick else
                                                                f" --pairs {args.pairs} --period {args.period:g} "
                                                                f"--work {args.work:g}"),
              "period_s": args.period, "work_s": args.work, "mj_step": release, "loop": loop,
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "load": os.getloadavg()},
              "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
