"""DeadlineWait: the composed realtime driver's wait for a period (sleep, then a spin without the GIL)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from sim_bridge_node.deadline_wait import DeadlineWait, _spin_until


@pytest.mark.parametrize("spin", [0.0, 0.0003])
def test_wait_returns_at_the_deadline_not_before(spin):
    waiter = DeadlineWait(spin)
    early = []
    for _ in range(50):
        deadline = time.perf_counter() + 0.001
        waiter.wait(deadline)
        early.append(deadline - time.perf_counter())
    assert max(early) <= 0.0  # never before the deadline
    waiter.wait(time.perf_counter() - 1.0)  # a deadline already passed returns at once


def test_the_spin_leaves_the_gil_to_other_threads():
    """A thread appending timestamps keeps running while the spin waits 0.2 s: compiled code that
    held the GIL would let no Python bytecode run until it returned (checked: ``nogil=False``
    gives 0 stamps inside, ``nogil=True`` millions)."""
    stamps: list[float] = []
    stop = threading.Event()

    def count() -> None:
        while not stop.is_set():
            stamps.append(time.perf_counter())

    timespec = np.zeros(2, dtype=np.int64)
    _spin_until(0, timespec)  # compiled before the measurement (the compiler holds the GIL)
    thread = threading.Thread(target=count)
    thread.start()
    try:
        time.sleep(0.02)
        t0 = time.perf_counter()
        _spin_until(time.perf_counter_ns() + 200_000_000, timespec)
        t1 = time.perf_counter()
    finally:
        stop.set()
        thread.join()
    inside = [s for s in stamps if t0 + 0.02 < s < t1 - 0.02]
    assert t1 - t0 >= 0.2
    assert len(inside) > 1000, len(inside)


@pytest.mark.parametrize("spin", [-1e-4, 0.02, float("nan")])
def test_bad_spin_is_refused(spin):
    with pytest.raises(ValueError, match="spin"):
        DeadlineWait(spin)


@pytest.mark.parametrize("spin", [-1e-4, 0.001])
def test_sim_bridge_refuses_a_realtime_spin_beyond_half_a_period(spin):
    from sim_bridge_node.node import PARAMETERS, _check

    params = {name: default for name, (default, _) in PARAMETERS.items()}
    _check(params)  # the defaults pass
    params["realtime_spin"] = spin
    with pytest.raises(ValueError, match="realtime_spin"):
        _check(params)


@pytest.mark.parametrize("spin", [0.0, 0.0003])
def test_before_spin_runs_once_per_wait_before_the_deadline(spin):
    """The realtime driver's warm-up hook runs once per period, after the sleep (never earlier than
    ``spin`` before the deadline), and the wait still returns no earlier than the deadline."""
    waiter = DeadlineWait(spin)
    calls: list[float] = []
    deadline = time.perf_counter() + 0.002
    waiter.wait(deadline, lambda: calls.append(time.perf_counter()))
    assert len(calls) == 1
    assert calls[0] >= deadline - spin - 1e-6  # after the sleep, which never ends early
    assert time.perf_counter() >= deadline
