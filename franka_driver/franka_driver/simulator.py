"""franky-sim (a MuJoCo FR3 behind the libfranka protocol) as a child process on 127.0.0.1 only,
started and stopped by its PID: the robot of the tests and of ``bench/bench_franka.py``.

    with FrankySim(Path("franky-sim.log")) as sim:   # then connect pylibfranka to 127.0.0.1
        ...

``FrankySim(log, frictionless=True)`` runs ``python -m franka_driver.franky_launch --frictionless``
instead: the same simulator with the arm joints' Coulomb friction removed (``franky_launch``);
``gear=True`` adds ``--gear`` (our gear task's shaft at the driver's default fixture position and
the gear welded to the hand), ``gear_load=True`` also ``--gear-load``.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

HOST = "127.0.0.1"
PORT = 1337  # libfranka's command port


def port_busy(host: str = HOST, port: int = PORT) -> bool:
    """True when something already listens on the robot port (another simulator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex((host, port)) == 0


class FrankySim:
    """``franky-sim -s mujoco --hostname 127.0.0.1`` as a child process (context manager).

    ``frictionless``: ``python -m franka_driver.franky_launch --frictionless`` instead, franky-sim's
    simulator built the same way with the arm joints' ``frictionloss`` zeroed (for measuring the
    controller's free-space error without the simulator's joint friction). ``gear``: with
    ``--gear`` (the gear task's shaft and gear, see ``franky_launch``); ``gear_load``: with
    ``--gear-load`` too (the gear configured as the robot's end-effector load)."""

    def __init__(self, log_path: Path, timeout: float = 60.0, frictionless: bool = False,
                 gear: bool = False, gear_load: bool = False) -> None:
        if port_busy():
            raise RuntimeError(f"{HOST}:{PORT} is taken: another robot simulator runs on this machine")
        if gear_load and not gear:
            raise ValueError("gear_load needs gear")
        self.log_path = log_path
        self.frictionless = frictionless
        self.gear = gear
        env = None
        flags = [f for f, on in (("--frictionless", frictionless), ("--gear", gear), ("--gear-load", gear_load)) if on]
        if flags:
            # this package importable in the child whatever its PYTHONPATH
            here = str(Path(__file__).resolve().parent.parent)
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p))
            cmd = [sys.executable, "-m", "franka_driver.franky_launch", *flags]
        else:
            cmd = [str(Path(sys.executable).parent / "franky-sim"), "-s", "mujoco", "--hostname", HOST]
        self._log = open(log_path, "w")
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + timeout
        while "Connect to the server" not in log_path.read_text():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"{' '.join(cmd)} did not start:\n{log_path.read_text()}")
            time.sleep(0.1)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self) -> None:
        """SIGINT (its clean shutdown), then SIGKILL, by PID."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._log.close()

    def __enter__(self) -> FrankySim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
