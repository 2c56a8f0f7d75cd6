"""The driver loop: the one thread that reads an arm's state, asks the composed controller for a
torque and writes it, as ros2_control's controller manager does for its hardware interfaces. ROS-free.

``DriverLoop`` owns what every driver shares: the loop thread (``start``, ``stop``), its scheduling
(SCHED_FIFO ``rt_priority``, ``nf_core.thread_priority``), the order of a tick and its timing
(``TickTiming``), and the episode hand-over with the controller's host (``begin_episode``). A driver
(the MuJoCo sim, the Franka arm) implements only its hardware side:

- ``read()``: the state (a robot blocks here until its next one) and the time the tick counts from;
- ``write(tau)``: the command (the lockstep sim steps with it);
- ``update()``: after the write (the sim's physics step and monitoring, the robot's kinematics);
- ``pace()``: wait for the next period (a self-timed sim; a robot's ``read`` paces itself);
- ``reset(seed, run, done)``: put the arm at an episode's start and start the episode.

Per tick, on the loop thread::

    host.service()                          # posted work (policy swaps, episode starts) in the slack
    stamp_ns, q, dq, started = read()
    write(host.tick(stamp_ns, q, dq, now))  # the controller: always finite (flow or safe hold)
    update(); timing.tick(...); pace()

Nothing slow runs between ``read`` and ``write``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any, Protocol

import numpy as np

from nf_core.episode import EpisodeRun
from nf_core.thread_priority import check_priority_allowed, enter_loop_thread, resolve_priority
from nf_core.tick_timing import LATE_AFTER, TickTiming


class EpisodeLoop(Protocol):
    """The part of the controller's loop a driver reads every tick."""

    episode: EpisodeRun | None  # the running episode, None between episodes


class LoopHost(Protocol):
    """The controller core as a driver hosts it (``nf_controller_node.host.ControllerHost``)."""

    loop: EpisodeLoop
    joint_names: list[str]  # order of q, dq given to ``tick``
    last_stamp_ns: int
    tau: np.ndarray  # the last torque ``tick`` returned (a copy, for monitoring)

    def call(self, fn: Callable[[], Any]) -> Future:
        """Run ``fn`` on the loop thread at its next ``service()``."""

    def service(self) -> int:
        """Run the posted work (loop thread, between ticks)."""

    def tick(self, stamp_ns: int, q: Sequence[float], dq: Sequence[float], now: float) -> np.ndarray:
        """The torque for a state: always finite."""

    def wants_tick(self, stamp_ns: int) -> bool:
        """False when the controller would leave the state unanswered (idle between episodes)."""

    def wait_for_work(self, timeout: float) -> bool:
        """Sleep until work is posted or ``timeout`` s pass."""

    def start_episode(self, run: EpisodeRun, first_stamp_ns: int, world_was_reset: bool) -> None:
        """Run ``run`` from the first state stamped at or after ``first_stamp_ns`` (loop thread)."""

    def set_task(self, depth: float, success: bool) -> None:
        """The task's latest insertion depth (m) and success, from the driver."""

    def warm(self) -> None:
        """Bring the tick's model and kernels back into the caches (no effect on torques)."""


class LoopLog(Protocol):
    """Where the loop thread says how it runs (an rclpy logger)."""

    def info(self, message: str) -> Any: ...

    def error(self, message: str) -> Any: ...

    def fatal(self, message: str) -> Any: ...


def loop_priority(requested: int, realtime_enforced: bool, loop: str) -> int:
    """The loop thread's SCHED_FIFO priority (0: normal scheduling) for the parameter value
    ``requested``, checked now, before anything starts: ``ValueError`` when a required priority is
    refused (never dropped silently)."""
    priority, required = resolve_priority(requested, realtime_enforced)
    refused = check_priority_allowed(priority, loop) if required else ""
    if refused:
        raise ValueError(refused)
    return priority


class DriverLoop:
    """One driver's loop thread around a ``LoopHost``; see the module docstring.

    ``timing``: the tick timing (None: not timed, e.g. the lockstep sim); ``rt_priority``: the loop
    thread's SCHED_FIFO priority (``loop_priority``; 0 normal scheduling); ``label``: how the log
    names the thread; ``answer_every_state``: a robot needs a command every cycle, so every state is
    ticked even when the controller idles (otherwise ``idle()`` decides).
    """

    def __init__(self, host: LoopHost, timing: TickTiming | None, rt_priority: int = 0,
                 label: str = "driver thread", thread_name: str = "driver-loop",
                 answer_every_state: bool = False) -> None:
        self.host = host
        self.timing = timing
        self.rt_priority = rt_priority
        self.label = label
        self.thread_name = thread_name
        self.answer_every_state = answer_every_state
        self.scheduling = "not started"  # the loop thread's, as it started ("fifo 99", "other 0")
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ------------------------------------------------------------------ hardware side (subclasses)
    def read(self) -> tuple[int, Any, Any, float]:
        """(stamp ns, q, dq, perf_counter time the tick counts from) of the arm's current state."""
        raise NotImplementedError

    def write(self, tau: np.ndarray) -> None:
        """Send the controller's torque ``tau`` (an internal buffer: use it now)."""
        raise NotImplementedError

    def update(self) -> None:
        """After the write: whatever the driver does with the rest of the period."""

    def idle(self) -> bool:
        """The controller leaves this state unanswered: True to skip the rest of the tick."""
        return False

    def late(self, started: float, written: float) -> bool:
        """Whether the tick counts as late; a robot's: the command missed the cycle."""
        return written - started > LATE_AFTER

    def pace(self) -> None:
        """Wait for the next period (a robot's ``read`` blocks instead)."""

    def reset(self, seed: int, run: EpisodeRun, done: Future) -> Callable[[], None]:
        """Called on the caller's thread (the slow preparation goes here); returns what runs on the
        loop thread: put the arm at the episode's start, ``host.start_episode(run, ...)``, complete
        ``done`` (now or later) or raise."""
        raise NotImplementedError

    # ------------------------------------------------------------------ episodes (any thread)
    def begin_episode(self, seed: int, run: EpisodeRun) -> Future:
        """Reset for ``run`` (``reset``) and start it, on the loop thread. The future is done when
        the episode runs, or holds why it did not; canceled before the reset ran, nothing happens."""
        done: Future = Future()
        on_loop = self.reset(seed, run, done)

        def start() -> None:
            if not done.cancelled():
                on_loop()

        def failed_to_start(posted: Future) -> None:
            exc = posted.exception()
            if exc is not None and not done.done():
                done.set_exception(exc)

        self.host.call(start).add_done_callback(failed_to_start)
        return done

    # ------------------------------------------------------------------ the loop
    def run(self, stop: threading.Event) -> None:
        """The loop until ``stop`` is set (on the calling thread; ``start`` gives it its own)."""
        self.ticks(stop)

    def ticks(self, stop: threading.Event) -> None:
        """Tick until ``stop`` is set: service, read, controller, write, update, timing, pace."""
        host, timing = self.host, self.timing
        read, write, update, pace = self.read, self.write, self.update, self.pace
        every = self.answer_every_state
        perf, monotonic = time.perf_counter, time.monotonic
        while not stop.is_set():
            host.service()
            stamp_ns, q, dq, started = read()
            if every or host.wants_tick(stamp_ns):
                write(host.tick(stamp_ns, q, dq, monotonic()))
            elif self.idle():
                continue
            written = perf()
            update()
            if timing is not None:
                timing.tick(started, written - started, late=self.late(started, written))
            pace()

    # ------------------------------------------------------------------ the thread
    def start(self, log: LoopLog) -> None:
        """The driver loop thread start: ``run`` on a thread of its own at ``rt_priority``."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._main, args=(log,), name=self.thread_name, daemon=True)
        self._thread.start()

    def _main(self, log: LoopLog) -> None:
        # a thread inherits its creator's policy: this one sets its own (0 also drops an inherited FIFO)
        self.scheduling, refused = enter_loop_thread(self.rt_priority)
        if refused:
            log.error(f"{self.label} at normal scheduling: {refused}")
        log.info(f"{self.label}: scheduling {self.scheduling}")
        try:
            self.run(self._stop)
        except Exception as exc:  # the loop must not die silently: the arm gets no more commands
            log.fatal(f"driver loop stopped: {exc!r}")
            raise

    def is_alive(self) -> bool:
        """The loop thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the loop and join its thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)
            self._thread = None
