"""Sensing-to-command timing as the driver sees it (realtime mode).

Every 1 ms tick the driver publishes state k. The command answering state k (its stamp label
says which state it answers) must arrive before the next tick, or step k+1 runs on an older
command: a deadline miss. A Franka aborts after about 20 missed cycles in a row, so the longest
run of consecutive misses is what decides whether a controller could drive the real arm.

``ResponseTiming`` is ROS-free: the node calls ``published`` at each tick and ``answered`` for
each command, with wall times from the same clock. Misses are counted from the first answer on
(before it no controller is running and the driver holds the arm). The latencies are summarised
with ``nf_core.tick_timing.latency_summary``, as the driver loops' are.
"""

from __future__ import annotations

import array
from collections import OrderedDict

_PENDING = 64  # states remembered for matching late answers
LONG_RUN = 5  # runs of at least this many misses are kept with their time (``long_runs``)


class ResponseTiming:
    """Latency from publishing a state to receiving the command that answers it, and misses."""

    def __init__(self, keep_all: bool = False) -> None:
        self._pending: OrderedDict[int, float] = OrderedDict()  # stamp -> publish time, unanswered
        self._last_stamp: int | None = None
        self._last_answered = True
        self.window: list[float] = []  # latencies (s) since the last ``take_window``
        self.all = array.array("d") if keep_all else None  # every latency (s), for a benchmark
        self.states = 0  # states published
        self.answers = 0  # states answered (first answer only)
        self.late_answers = 0  # answers that came after the next state was published
        self.misses = 0  # states not answered before the next one
        self.run = 0  # current run of consecutive misses
        self.longest_run = 0
        self.long_runs: list[tuple[float, int]] = []  # (s since the first answer, length) of runs >= LONG_RUN
        self._first_answer: float | None = None
        self._run_start = 0.0

    def published(self, stamp_ns: int, now: float) -> None:
        """State ``stamp_ns`` went out at ``now`` (s); closes the deadline of the previous state."""
        if self._last_stamp is not None and self.answers:  # misses count from the first answer on
            if self._last_answered:
                if self.run >= LONG_RUN:
                    self.long_runs.append((self._run_start - self._first_answer, self.run))
                self.run = 0
            else:
                if self.run == 0:
                    self._run_start = now
                self.misses += 1
                self.run += 1
                self.longest_run = max(self.longest_run, self.run)
        self._last_stamp = stamp_ns
        self._last_answered = False
        self._pending[stamp_ns] = now
        while len(self._pending) > _PENDING:
            self._pending.popitem(last=False)
        self.states += 1

    def answered(self, stamp_ns: int, now: float) -> float | None:
        """A command answering state ``stamp_ns`` arrived at ``now``; returns its latency (s) or
        None when the state is unknown or already answered."""
        sent = self._pending.pop(stamp_ns, None)
        if sent is None:
            return None
        latency = now - sent
        if self._first_answer is None:
            self._first_answer = now
        self.answers += 1
        if stamp_ns == self._last_stamp:
            self._last_answered = True
        else:
            self.late_answers += 1
        self.window.append(latency)
        if self.all is not None:
            self.all.append(latency)
        return latency

    def take_window(self) -> list[float]:
        """The latencies since the last call (and start a new window)."""
        window, self.window = self.window, []
        return window

    def counters(self) -> dict[str, int]:
        """Counts since the start."""
        return {"states": self.states, "answers": self.answers, "late_answers": self.late_answers,
                "deadline_misses": self.misses, "longest_miss_run": self.longest_run}

