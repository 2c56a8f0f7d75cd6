"""Waiting for a control period's deadline on a machine without a realtime kernel. ROS-free.

A sleeping thread wakes late: on this project's 2-core VM a bare Python loop that sleeps to 1 ms
deadlines wakes a median 0.1 ms late and more than 1 ms late for 0.2-0.3 % of the periods (the
idle virtual CPU has to be woken); a loop that spins to the deadline is more than 1 ms late for
0.04 %. A driver thread that spins in Python holds the GIL, though, and starves the executor and
the rest of its process (tried: the composed stack got worse).

``DeadlineWait(spin)`` does both: it sleeps until ``spin`` seconds before the deadline, then spins
the rest in compiled code that does not hold the GIL (numba ``nogil`` reading ``CLOCK_MONOTONIC``,
the clock of ``time.perf_counter`` on Linux). The cost is up to ``spin`` seconds of one core per
period. ``spin`` 0 is a plain ``time.sleep``.
"""

from __future__ import annotations

import ctypes
import math
import time
from collections.abc import Callable

import numpy as np
from numba import njit

CLOCK_MONOTONIC = 1  # Linux clockid_t (time.perf_counter's clock)

_libc = ctypes.CDLL(None)
_clock_gettime = _libc.clock_gettime
_clock_gettime.argtypes = (ctypes.c_int, ctypes.c_void_p)
_clock_gettime.restype = ctypes.c_int


@njit(nogil=True)  # not cached: the compiled code embeds this process's address of clock_gettime
def _spin_until(deadline_ns: int, timespec: np.ndarray) -> int:
    """Busy-wait without the GIL until CLOCK_MONOTONIC >= ``deadline_ns``; returns the time (ns)."""
    address = timespec.ctypes.data
    while True:
        _clock_gettime(CLOCK_MONOTONIC, address)
        now = timespec[0] * 1_000_000_000 + timespec[1]
        if now >= deadline_ns:
            return now


class DeadlineWait:
    """``wait(deadline)``: return at ``time.perf_counter() >= deadline`` (s); see the module docstring.
    One instance per thread (it owns the buffer the spin reads the clock into)."""

    def __init__(self, spin: float) -> None:
        if not (math.isfinite(spin) and 0.0 <= spin <= 0.01):
            raise ValueError(f"spin must be between 0 and 0.01 s, got {spin}")
        self.spin = float(spin)
        self._timespec = np.zeros(2, dtype=np.int64)  # struct timespec {tv_sec, tv_nsec} on 64-bit Linux
        if self.spin > 0.0:
            now = _spin_until(0, self._timespec)  # compile now, not in the first period
            if abs(now - time.perf_counter_ns()) > 1_000_000:
                raise RuntimeError("CLOCK_MONOTONIC is not time.perf_counter's clock here: use spin 0")

    def wait(self, deadline: float, before_spin: Callable[[], None] | None = None) -> None:
        """Sleep until ``spin`` s before ``deadline`` (perf_counter seconds), then spin to it.
        ``before_spin`` (if given) runs once, between the sleep and the spin (a cache warm-up)."""
        rest = deadline - time.perf_counter() - self.spin
        if rest > 0.0:
            time.sleep(rest)
        if before_spin is not None:
            before_spin()
        if self.spin > 0.0:
            _spin_until(int(deadline * 1e9), self._timespec)
