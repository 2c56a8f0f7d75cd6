"""Timing of a driver's control loop that hosts the controller (the composed sim, the Franka
driver), measured on the driver's own clock (``time.perf_counter``), and the one summary of
latencies (``latency_summary``) every loop, driver and controller reports. ROS-free.

The driver says what "late" means for it: the sim schedules its own ticks (a tick that starts
more than a millisecond after its schedule is late); a robot's driver is late when the command
leaves more than a millisecond after the state arrived.
"""

from __future__ import annotations

import array

import numpy as np

LATE_AFTER = 0.001  # s: the lateness both drivers count against (one 1 kHz cycle)
LONG_LATE_RUN = 3  # runs of at least this many late ticks are kept with their time (``long_runs``)
WINDOW = 100_000  # latencies kept between two ``take_window`` calls


class TickTiming:
    """Counts and latencies of a driver loop's ticks: state -> command latency, tick period,
    late ticks and the runs of them; with ``keep_all`` every latency and period (benchmarks)."""

    def __init__(self, keep_all: bool = False) -> None:
        self.latency = array.array("d")  # state read -> command written, s (kept when keep_all)
        self.periods = array.array("d")  # start of a tick -> start of the next one, s (kept when keep_all)
        self._keep = keep_all
        self._window: list[float] = []
        self.ticks = 0
        self.late = 0
        self.run = 0  # late ticks in a row, now
        self.longest_run = 0
        self.long_runs: list[tuple[float, int]] = []  # (s since the first tick, length) of runs >= LONG_LATE_RUN
        self.resyncs = 0  # sim: schedule restarted after falling more than 10 periods behind
        self.missed_cycles = 0  # robot: cycles between two reads beyond the first
        self._t0: float | None = None
        self._last_start: float | None = None
        self._run_start = 0.0

    def tick(self, started: float, latency: float, late: bool) -> None:
        """One tick that began at ``started`` (s, perf_counter) and took ``latency`` (s) from the
        state to the command; ``late`` as the driver defines it."""
        if self._t0 is None:
            self._t0 = started
        if self._last_start is not None and self._keep:
            self.periods.append(started - self._last_start)
        self._last_start = started
        self.ticks += 1
        if self._keep:
            self.latency.append(latency)
        if len(self._window) < WINDOW:
            self._window.append(latency)
        if late:
            if self.run == 0:
                self._run_start = started - self._t0
            self.late += 1
            self.run += 1
            self.longest_run = max(self.longest_run, self.run)
        else:
            self._end_run()

    def restart(self) -> None:
        """A new control session: the next period is not measured across the gap, a run ends."""
        self._last_start = None
        self._end_run()

    def _end_run(self) -> None:
        if self.run >= LONG_LATE_RUN:
            self.long_runs.append((self._run_start, self.run))
        self.run = 0

    def take_window(self) -> list[float]:
        """Latencies (s) since the last call."""
        window, self._window = self._window, []
        return window

    def counters(self) -> dict[str, int]:
        """Counts for diagnostics and benchmarks."""
        return {"ticks": self.ticks, "late_ticks": self.late, "longest_late_run": self.longest_run,
                "resyncs": self.resyncs, "missed_cycles": self.missed_cycles}


def latency_summary(values_s: array.array | np.ndarray | list[float]) -> dict[str, float]:
    """count, p50/p90/p99/p99.9/max of durations given in s, in microseconds (all 0 when empty).
    The one latency summary of the stack: diagnostics and logs prefix these keys, never rename them."""
    a = np.frombuffer(values_s, dtype=np.float64) if isinstance(values_s, array.array) \
        else np.asarray(values_s, dtype=np.float64)
    if a.size == 0:
        return {"count": 0, "p50_us": 0.0, "p90_us": 0.0, "p99_us": 0.0, "p999_us": 0.0, "max_us": 0.0}
    p50, p90, p99, p999 = np.percentile(a, [50, 90, 99, 99.9]) * 1e6
    return {"count": int(a.size), "p50_us": float(p50), "p90_us": float(p90), "p99_us": float(p99),
            "p999_us": float(p999), "max_us": float(a.max() * 1e6)}
