"""Child processes of the stack runner: started with a private ROS domain on loopback, output
prefixed, forwarded and kept in a log file, watched for ready lines, stopped by PID
(SIGINT, then SIGTERM, then SIGKILL)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO


class ManagedProcess:
    """One child process whose output is prefixed and forwarded (and kept in a log file)."""

    def __init__(self, name: str, argv: Sequence[str], env: dict[str, str], log_dir: Path, echo: bool = True,
                 watch: Sequence[str] = ()) -> None:
        self.name = name
        self.argv = list(argv)
        log_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = log_dir / f"{name}.log"
        self._log: IO[str] = self.log_path.open("w")
        self.proc = subprocess.Popen(self.argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1, start_new_session=True)
        self._echo = echo
        self._seen = threading.Condition()
        self._unseen = list(watch)  # watched texts no output line has contained yet (wait_for_watched)
        self._thread = threading.Thread(target=self._forward, name=f"log-{name}", daemon=True)
        self._thread.start()

    def _forward(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._log.write(line)
            self._log.flush()
            if self._unseen:
                with self._seen:
                    self._unseen = [w for w in self._unseen if w not in line]
                    self._seen.notify_all()
            if self._echo:
                sys.stdout.write(f"[{self.name}] {line}" if not line.startswith("[learner]") else line)
                sys.stdout.flush()

    def wait_for_watched(self, timeout: float, alive: Sequence[ManagedProcess] = (),
                         texts: Sequence[str] | None = None) -> list[str]:
        """Wait until every ``watch`` text given at start (or only ``texts`` of them) has appeared in a
        line of output; the texts still missing (empty on success) when ``timeout`` s pass or this
        process or one of ``alive`` exits."""
        deadline = time.monotonic() + timeout
        with self._seen:
            while True:
                missing = [t for t in self._unseen if texts is None or t in texts]
                left = deadline - time.monotonic()
                if not missing or left <= 0 or not all(p.running() for p in (self, *alive)):
                    return missing
                self._seen.wait(timeout=min(left, 0.2))

    @property
    def pid(self) -> int:
        """The child's PID."""
        return self.proc.pid

    def running(self) -> bool:
        """True while the child has not exited."""
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGINT, then SIGTERM, then SIGKILL (by PID), waiting up to ``timeout`` s at each; exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if not self.running():
                break
            os.kill(self.pid, sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                continue
        self._thread.join(timeout=2.0)
        self._log.close()
        return self.proc.poll()


def ros_environment(domain_id: int | None = None) -> dict[str, str]:
    """This process's environment with loopback-only discovery and one domain id."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if domain_id is None:
        domain_id = int(env.get("ROS_DOMAIN_ID") or (100 + os.getpid() % 100))
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONUNBUFFERED"] = "1"
    return env
