"""Reliability of learning on the robot path under reflexes: ``make run-franka`` on franky-sim with a reflex
injected every ``--every`` seconds (``kill -USR1`` to the franky-sim launcher, as docs/hardware.md gives it),
then a tally from the run folder: iterations, episodes by outcome, reflexes, recoveries.

    python experiments/reflex_run.py --iterations 20 --every 150 --out runs/reflex20

Run it alone on the machine (the simulator must keep real time). Answer in docs/results/robot_reliability.md.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

LAUNCHER = "nf_bringup.testing.franky"


def launcher_pid(parent: int) -> int | None:
    """PID of the franky-sim launcher among ``parent``'s children (None until it runs)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == parent and LAUNCHER in cmdline:
            return int(entry.name)
    return None


def tally(out: Path) -> dict:
    """What the run folder says: iterations, episodes by outcome, reflexes and recoveries (the driver logs a
    libfranka error only when its text changes, so the log cannot count them: the bag's counter does)."""
    metrics = json.loads((out / "learner" / "metrics.json").read_text())
    arms = json.loads((out / "learner" / "arms.json").read_text())
    outcomes: dict[str, int] = {}
    for counts in arms["arms"].values():
        for k, v in counts.items():
            if isinstance(v, int):
                outcomes[k] = outcomes.get(k, 0) + v
    logs = out / "logs"
    reflexes = (logs / "franky-sim.log").read_text().count("SIGUSR1")
    recoveries = None
    try:
        from nf_bags.reader import read_messages

        for d in read_messages(out / "bag", ["/diagnostics"]):
            for status in d.msg.status:
                if status.name == "franka_driver: robot":
                    values = {kv.key: kv.value for kv in status.values}
                    recoveries = int(values.get("recoveries", recoveries or 0))
    except Exception as exc:  # no bag: say so
        print(f"recoveries not read from the bag: {exc}", file=sys.stderr)
    from learner_node.trainer import run_evaluations

    evaluations = {label: e.get("success_rate") for label, e in run_evaluations(out / "learner")}
    return {"iterations": len(metrics), "dropped_episodes": sum(r["dropped_episodes"] for r in metrics),
            "training_success": [round(r["success_rate"], 2) for r in metrics], "dispatches": outcomes,
            "reflexes_injected": reflexes, "recoveries": recoveries,
            "evaluations": evaluations}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--every", type=float, default=150.0, help="s between reflexes")
    ap.add_argument("--first", type=float, default=90.0, help="s before the first reflex")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    cmd = [sys.executable, "-m", "nf_bringup.robot_run", "--iterations", str(args.iterations), "--out", str(args.out)]
    run = subprocess.Popen(cmd)
    t0 = time.monotonic()
    next_reflex = t0 + args.first
    sent = 0
    try:
        while run.poll() is None:
            time.sleep(1.0)
            if time.monotonic() >= next_reflex:
                pid = launcher_pid(run.pid)
                if pid is not None:
                    os.kill(pid, signal.SIGUSR1)
                    sent += 1
                    print(f"[reflex_run] reflex {sent} at {time.monotonic() - t0:.0f} s", flush=True)
                next_reflex += args.every
    except KeyboardInterrupt:
        run.send_signal(signal.SIGINT)
        run.wait()
    summary = {"command": " ".join(cmd), "exit_code": run.returncode, "wall_s": round(time.monotonic() - t0),
               "reflexes_sent": sent, **tally(args.out)}
    (args.out / "reflex_run.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0 if run.returncode == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
