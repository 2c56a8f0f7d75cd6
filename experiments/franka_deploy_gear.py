"""A trained gear policy deployed over libfranka onto franky-sim's gear fixture: does it insert?

Starts ``nf_bringup.testing.franky --gear --gear-load`` (``--frictionless`` passes on), ``nf_franka_stack``
(``config/franka.yaml``, idle_mode policy) and ``deploy_policy`` twice with the given checkpoint:
first with x_ref above the fixture (``--above``, the driver's reset pose), then with x_ref at the
fixture's goal (``--goal``); meanwhile it prints the driver's TCP, insertion depth and success from
``/diagnostics`` every 3 s. Own ROS_DOMAIN_ID, loopback only; every process stopped by PID.

    train --config config/gear_learn.yaml --iterations 30 --out runs/gear30
    PYTHONPATH=bench:$PYTHONPATH python experiments/franka_deploy_gear.py runs/gear30/checkpoint.pt [--frictionless]

A probe for docs/hardware.md (the policy is learned on the MuJoCo Panda, the fixture sits on
franky-sim's FR3 20 mm lower, so the goal differs), not a benchmark.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import sources  # noqa: F401  (the package sources first on sys.path)

REPO = Path(__file__).resolve().parent.parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--frictionless", action="store_true", help="franky-sim without joint friction")
    parser.add_argument("--above", type=float, nargs=3, default=[0.5, 0.0, 0.25], metavar=("X", "Y", "Z"))
    parser.add_argument("--goal", type=float, nargs=3, default=[0.5, 0.0, 0.05], metavar=("X", "Y", "Z"))
    parser.add_argument("--seconds", type=float, default=20.0, help="at the goal (s)")
    args = parser.parse_args()
    if not args.checkpoint.is_file():
        parser.error(f"no checkpoint {args.checkpoint}")
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from nf_bringup.processes import ManagedProcess, allocate_domain_id, isolate, ros_env

    domain = allocate_domain_id()
    env = ros_env(domain)
    isolate(os.environ, domain, sources=False)  # this process's node too: loopback, UDP
    py = sys.executable
    procs: list[ManagedProcess] = []
    rclpy.init(args=["--ros-args"], domain_id=domain)
    node = rclpy.create_node("franka_deploy_gear")
    last: dict[str, str] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.startswith("franka_driver: robot"):
                last.update({kv.key: kv.value for kv in status.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag,
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def watch(seconds: float) -> None:
        t0 = time.monotonic()
        due = t0
        while time.monotonic() < t0 + seconds:
            rclpy.spin_once(node, timeout_sec=0.05)
            if last and time.monotonic() >= due:
                print(f"  {time.monotonic() - t0:5.1f} s  TCP {last.get('tcp')}  depth {last.get('insertion_depth')} m"
                      f"  success {last.get('success')}", flush=True)
                due += 3.0

    with tempfile.TemporaryDirectory() as tmp:
        logs = Path(tmp)
        try:
            sim = [py, "-m", "nf_bringup.testing.franky", "--gear", "--gear-load"]
            procs.append(ManagedProcess("franky", sim + (["--frictionless"] if args.frictionless else []), env,
                                        logs, echo=False))
            time.sleep(5.0)
            procs.append(ManagedProcess("stack", [
                py, "-m", "nf_bringup.franka_stack", "--ros-args",
                "--params-file", str(REPO / "config" / "franka.yaml"),
                "-p", "franka_driver:robot_ip:=127.0.0.1", "-p", "franka_driver:realtime:=ignore",
                "-p", "nf_controller:idle_mode:=policy"], env, logs, echo=False))
            time.sleep(8.0)
            for name, x_ref, version, seconds in (("above", args.above, 100000, 12.0),
                                                  ("goal", args.goal, 100001, args.seconds)):
                print(f"x_ref {x_ref} ({name}):", flush=True)
                procs.append(ManagedProcess(f"deploy_{name}", [
                    py, "-m", "learner_node.deploy", str(args.checkpoint), "--x-ref", *map(str, x_ref),
                    "--version", str(version), "--seconds", str(seconds)], env, logs, echo=False))
                watch(seconds)
        finally:
            for proc in reversed(procs):
                proc.stop()
            node.destroy_node()
            rclpy.shutdown()
        exceptions = (logs / "stack.log").read_text().lower().count("exception")
    print(f"lines mentioning an exception in the stack's log: {exceptions}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
