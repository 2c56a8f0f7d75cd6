"""The controller core as a driver hosts it: one direct call per control tick; everything slow is
posted from other threads and runs between ticks. ROS-free.

A driver (the composed MuJoCo bridge, the Franka driver, or the standalone topic node) owns the
loop that reads the arm's state and writes its torque. Each control period it calls::

    host.service()                                   # between ticks: posted work, if any
    tau = host.tick(stamp_ns, q, dq, time.monotonic())  # state -> torque, always finite

Nothing else runs on that thread. Whoever owns the slow side (the ``nf_controller`` node's
executor: policy messages, the RunEpisode action, status, diagnostics) talks to the loop only
through two doors:

- ``call(fn)`` queues ``fn`` to run on the driver thread at the next ``service()`` and returns a
  ``concurrent.futures.Future`` of its result: policy swaps, episode starts, world resets;
- ``drain()`` hands over what the ticks produced since the last drain (``HostEvent``: rollout
  chunks, episode ends, new faults), to publish or log outside the tick. ``notify``, if set, is
  called on the driver thread when a tick queues events (the node passes a guard condition's
  ``trigger``: its executor wakes for events instead of polling).

Both are ``collections.deque`` operations (atomic under the GIL) plus an ``Event`` for a driver
that sleeps while idle (``wait_for_work``). The slow side never holds a lock the tick needs.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from nf_core.episode import Chunk, EpisodeRun

from .control_loop import ControlLoop

T = TypeVar("T")

CHUNK, EPISODE_END, FAULT = "chunk", "episode_end", "fault"  # HostEvent kinds


@dataclass
class HostEvent:
    """Something a tick produced that the slow side publishes: a rollout chunk of ``run``, the end
    of ``run`` (``text`` empty when it completed, else why it was aborted), or a new fault."""

    kind: str
    run: EpisodeRun | None = None
    chunk: Chunk | None = None
    text: str = ""
    stamp_ns: int = 0  # stamp of the state that produced it (a chunk: of its first sample)


class EpisodeDriver(Protocol):
    """What a composed driver offers the controller node for episodes."""

    def begin_episode(self, seed: int, run: EpisodeRun) -> Future:
        """Reset the world for an episode (sim: at once with ``seed``; robot: a motion to the start
        pose), then ``host.start_episode(run, ...)`` on the driver thread. The future is done when
        the episode runs, or holds the exception that stopped it."""


class ControllerHost:
    """A ``ControlLoop`` behind a per-tick call and a work queue; see the module docstring."""

    def __init__(self, loop: ControlLoop, joint_names: Sequence[str] | None = None) -> None:
        self.loop = loop
        self.joint_names = list(joint_names or loop.joints.joint_names)  # order of q, dq given to tick
        self._names = tuple(self.joint_names)  # what tick passes on: an immutable list is mapped once
        self._inbox: deque[tuple[Callable[[], Any], Future]] = deque()
        self._outbox: deque[HostEvent] = deque()
        self._work = threading.Event()
        self.last_stamp_ns = 0  # stamp of the last state ticked
        self.tau = np.zeros(loop.n)  # last torque returned (a copy, for status and monitoring)
        self.notify: Callable[[], None] | None = None  # called (driver thread) when events are queued

    # ------------------------------------------------------------------ slow side (any thread)
    def call(self, fn: Callable[[], T]) -> Future:
        """Run ``fn`` on the driver thread at its next ``service()``; the future holds its result
        (or the exception it raised)."""
        future: Future = Future()
        self._inbox.append((fn, future))
        self._work.set()
        return future

    def drain(self) -> list[HostEvent]:
        """Everything the ticks produced since the last call, oldest first."""
        out = []
        box = self._outbox
        while box:
            out.append(box.popleft())
        return out

    # ------------------------------------------------------------------ driver thread
    def service(self) -> int:
        """Run the work posted with ``call`` (the driver calls this between ticks). Returns how many
        functions ran; costs one deque check when nothing is queued."""
        inbox = self._inbox
        if not inbox:
            return 0
        n = 0
        self._work.clear()
        while inbox:
            fn, future = inbox.popleft()
            n += 1
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller through the future
                future.set_exception(exc)
        return n

    def warm(self) -> None:
        """Driver thread, before it waits for the next state: ``ControlLoop.warm`` (no effect on
        the next torque; it only brings the tick's model and kernels back into the caches)."""
        self.loop.warm()

    def wait_for_work(self, timeout: float) -> bool:
        """Sleep until something is posted (or ``timeout`` s pass): for a driver with nothing to tick."""
        if self._inbox:
            return True
        return self._work.wait(timeout)

    def wants_tick(self, stamp_ns: int) -> bool:
        """False when the loop would leave the state stamped ``stamp_ns`` unanswered (idle_mode
        "pause" outside an episode): a lockstep driver then waits instead of stepping."""
        return self.loop.answers(stamp_ns)

    def set_task(self, depth: float, success: bool) -> None:
        """The task's latest insertion depth (m) and success flag, from the driver itself (simulator
        or kinematics); a task topic goes through ``ControlLoop.on_task_status`` (checked) instead."""
        loop = self.loop
        loop.depth = depth
        loop.task_success = success

    @property
    def depth(self) -> float:
        """Latest insertion depth (m; NaN when unknown)."""
        return self.loop.depth

    @property
    def success(self) -> bool:
        """Latest task success flag."""
        return self.loop.task_success

    def start_episode(self, run: EpisodeRun, first_stamp_ns: int, world_was_reset: bool) -> None:
        """Driver thread: run ``run`` from the first state stamped at or after ``first_stamp_ns``.
        ``world_was_reset``: the arm was put somewhere new (a simulator's reset), so the first
        command is not rate-limited against the last one; a robot that moved there says False."""
        self.loop.start_episode(run, first_stamp_ns, world_was_reset=world_was_reset)

    def tick(self, stamp_ns: int, q: Sequence[float], dq: Sequence[float], now: float,
             names: Sequence[str] | None = None) -> np.ndarray:
        """Torque (Nm, ``joint_names`` order) for the state (q rad, dq rad/s) stamped ``stamp_ns``,
        read at monotonic time ``now`` (s). Always finite: the flow controller, or the safe hold.
        ``names``: the state's joint names when they may differ from ``joint_names`` (a topic).

        Streams the running episode's finished chunks and ends it when it is done or a fault latched
        (events for ``drain``). The array is an internal buffer: use it before the next tick.
        """
        t0 = time.perf_counter()
        loop = self.loop
        tau, new_fault = loop.on_joint_state(self._names if names is None else names, q, dq, stamp_ns, now)
        self.last_stamp_ns = stamp_ns
        missed = loop.record_latency(time.perf_counter() - t0)
        fault = new_fault or missed
        if fault:
            self._emit(HostEvent(FAULT, text=fault, stamp_ns=stamp_ns))
        run = loop.episode
        if run is not None and run.steps:
            if run.closed >= run.next_chunk_closes:
                for chunk in run.ready_chunks():  # stamped as its first sample (RolloutChunk.msg)
                    first_ns = loop.episode_start_ns + round(float(chunk.t[0]) * 1e9) if len(chunk.t) else stamp_ns
                    self._emit(HostEvent(CHUNK, run=run, chunk=chunk, stamp_ns=first_ns))
            if fault or loop.fault:
                self.end_episode(f"aborted: safe hold ({fault or loop.fault})")
            elif run.done:
                self.end_episode("")
        self.tau[:] = tau
        return tau

    def _emit(self, event: HostEvent) -> None:
        self._outbox.append(event)
        if self.notify is not None:
            self.notify()

    def end_episode(self, problem: str) -> None:
        """End the running episode (driver thread): ``problem`` empty when it completed."""
        loop = self.loop
        run = loop.end_episode()
        if run is not None:
            self._emit(HostEvent(EPISODE_END, run=run, text=problem, stamp_ns=self.last_stamp_ns))


def success_of(depth: float, success: bool) -> bool:
    """An episode's success: the reported flag, only when a finite depth came with it."""
    return bool(success) if math.isfinite(depth) else False
