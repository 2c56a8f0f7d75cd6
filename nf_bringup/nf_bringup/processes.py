"""Child processes of the stack, the tests and the benchmarks: the one definition of a ROS child's
environment (its own domain, discovery on loopback only, UDP transport, the package sources
importable), a domain-id allocator, and processes started with their output in a log file and
stopped by their PID (SIGINT first, then harder signals).
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, MutableMapping, Sequence
from pathlib import Path
from typing import IO

# the checkout's folders whose sources a child imports (ament_python packages and plain nf_bags)
PACKAGE_SOURCES = ("nf_core", "nf_controller_node", "learner_node", "sim_bridge_node", "nf_bringup", "franka_driver",
                   "bags")
# Processes are killed by PID (SIGKILL when they do not stop); Fast DDS's shared-memory transport leaves
# a killed peer's segments in /dev/shm, where another peer can block inside C++ for good: UDP on loopback.
TRANSPORTS = "UDPv4"
STOP_SIGNALS = (signal.SIGINT, signal.SIGKILL)
_domains = itertools.count()


def stop_on_signals() -> None:
    """Make SIGINT, SIGTERM and SIGHUP raise ``KeyboardInterrupt`` in the main thread, so a runner stops
    its children and writes its summary however it is stopped: Ctrl-C, ``kill <PID>``, a closed
    terminal, or a job started in the background by a shell without job control (which starts it with
    SIGINT ignored: ``nohup make run-franka &`` could not be interrupted, and SIGTERM left franky-sim, the
    stack and the learner running without their runner)."""

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, interrupt)


def source_root() -> Path | None:
    """The checkout holding the package sources (None for a copy installed outside one)."""
    for parent in Path(__file__).resolve().parents:
        if (parent / "nf_core" / "nf_core").is_dir() and (parent / "nf_bringup" / "nf_bringup").is_dir():
            return parent
    return None


REPO = source_root()


def source_paths() -> list[str]:
    """The package source folders of the checkout (empty outside one)."""
    return [str(REPO / p) for p in PACKAGE_SOURCES] if REPO is not None else []


def use_sources() -> None:
    """Put the package sources first on this process's ``sys.path`` (scripts run from a checkout)."""
    sys.path[:0] = [p for p in source_paths() if p not in sys.path]


def allocate_domain_id() -> int:
    """A ROS_DOMAIN_ID: distinct per call in this process, spread by PID across processes; within
    ``NF_DOMAIN_IDS`` (``first-last``) when set, so that processes given disjoint ranges never meet."""
    spec = os.environ.get("NF_DOMAIN_IDS", "")
    first, last = (int(x) for x in spec.split("-")) if spec else (1, 200)
    return first + (os.getpid() * 7 + next(_domains)) % (last - first + 1)


def isolate(env: MutableMapping[str, str], domain_id: int | None, sources: bool = True,
            paths: Sequence[str | Path] = (), peers: Sequence[str] = ()) -> MutableMapping[str, str]:
    """Set ``env`` (a copy, or ``os.environ`` before this process starts ROS) for a ROS process:
    ``domain_id`` (None: keep the one it has), discovery on loopback only (or, with ``peers``, over
    the subnet to those unicast addresses: hosts of a fleet), UDP transport, unbuffered output;
    ``paths`` and (``sources``) the package sources first on PYTHONPATH."""
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    if peers:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
        env["ROS_STATIC_PEERS"] = ";".join(peers)
    else:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        env.pop("ROS_STATIC_PEERS", None)
    env["FASTDDS_BUILTIN_TRANSPORTS"] = TRANSPORTS
    env["PYTHONUNBUFFERED"] = "1"
    front = [str(p) for p in paths] + (source_paths() if sources else [])
    if front:
        env["PYTHONPATH"] = os.pathsep.join([*front, *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])])
    return env


def ros_env(domain_id: int | None, sources: bool = True, paths: Sequence[str | Path] = (),
            peers: Sequence[str] = (), **extra: str) -> dict[str, str]:
    """This process's environment for a ROS child (``isolate``), then ``extra`` variables on top."""
    env = dict(os.environ)
    isolate(env, domain_id, sources, paths, peers)
    env.update(extra)
    return env


def stop_process(proc: subprocess.Popen, timeout: float = 10.0,
                 signals: Sequence[int] = STOP_SIGNALS) -> int | None:
    """Send ``signals`` in turn to the process (by its PID), waiting up to ``timeout`` s after each
    until it exits; its exit code (None if it outlived them all)."""
    for sig in signals:
        if proc.poll() is not None:
            break
        os.kill(proc.pid, sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


class RosProcess:
    """``python <args>`` in ROS domain ``domain_id`` (``ros_env``), output in ``log_path`` (none:
    discarded); stopped by PID. ``prefix``: a command that execs Python in its place (same PID, e.g.
    ``ip netns exec <host>``); ``paths``: folders put first on its PYTHONPATH; ``peers``: discover
    over the subnet with these unicast peers; ``extra``: more environment variables."""

    def __init__(self, args: Sequence[str], domain_id: int, log_path: Path | None = None,
                 prefix: Sequence[str] = (), paths: Sequence[str | Path] = (), peers: Sequence[str] = (),
                 **extra: str) -> None:
        self.log_path = log_path
        self._out = open(log_path, "w") if log_path else None  # closed in stop
        env = ros_env(domain_id, paths=paths, peers=peers, **extra)
        self.proc = subprocess.Popen([*prefix, sys.executable, *args], env=env,
                                     stdout=self._out or subprocess.DEVNULL, stderr=subprocess.STDOUT)

    @property
    def pid(self) -> int:
        """The child's PID."""
        return self.proc.pid

    def alive(self) -> bool:
        """True while the child has not exited."""
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGINT, then SIGKILL (by PID), waiting up to ``timeout`` s at each; the exit code."""
        code = stop_process(self.proc, timeout)
        if self._out is not None:
            self._out.close()
        return code

    def log(self) -> str:
        """Everything the child wrote so far."""
        return self.log_path.read_text() if self.log_path and self.log_path.exists() else ""

    def __enter__(self) -> RosProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ManagedProcess:
    """One child process of the stack runner, in its own session, whose output is prefixed and
    forwarded, kept in ``log_dir/<name>.log`` and watched for the ``watch`` texts."""

    def __init__(self, name: str, argv: Sequence[str], env: dict[str, str], log_dir: Path, echo: bool = True,
                 watch: Sequence[str] = (), on_line: Callable[[str], None] | None = None) -> None:
        self.name = name
        self._on_line = on_line  # called with each output line (on the forwarding thread)
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
            if self._on_line is not None:
                self._on_line(line)

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
        code = stop_process(self.proc, timeout, (signal.SIGINT, signal.SIGTERM, signal.SIGKILL))
        self._thread.join(timeout=2.0)
        self._log.close()
        return code
