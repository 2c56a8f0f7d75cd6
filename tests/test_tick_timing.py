"""The one tick-timing record of both drivers that host the controller (composed sim, Franka)."""

import pytest

from nf_core.tick_timing import LONG_LATE_RUN, TickTiming, latency_summary


def feed(t: TickTiming, lateness: list[bool], start: float = 0.0, dt: float = 1e-3) -> float:
    for k, late in enumerate(lateness):
        t.tick(start + k * dt, 1e-4, late)
    return start + len(lateness) * dt


def test_late_ticks_runs_and_long_runs_with_the_time_they_began():
    t = TickTiming(keep_all=True)
    feed(t, [False, True, False] + [True] * LONG_LATE_RUN + [False, False])
    assert t.ticks == 3 + LONG_LATE_RUN + 2
    assert t.late == 1 + LONG_LATE_RUN and t.longest_run == LONG_LATE_RUN
    assert t.long_runs == [(pytest.approx(3e-3), LONG_LATE_RUN)]  # the short run is not kept
    assert len(t.periods) == t.ticks - 1 and len(t.latency) == t.ticks


def test_restart_measures_no_period_across_the_gap_and_ends_a_run():
    t = TickTiming(keep_all=True)
    end = feed(t, [True] * (LONG_LATE_RUN + 1))
    t.restart()
    feed(t, [False, False], start=end + 5.0)
    assert max(t.periods) < 2e-3  # the 5 s between the sessions is not a period
    assert t.long_runs == [(0.0, LONG_LATE_RUN + 1)] and t.run == 0


def test_without_keep_all_only_the_bounded_window_is_kept():
    t = TickTiming()
    feed(t, [False] * 10)
    assert len(t.latency) == 0 and len(t.periods) == 0
    assert len(t.take_window()) == 10 and t.take_window() == []
    assert t.counters() == {"ticks": 10, "late_ticks": 0, "longest_late_run": 0, "resyncs": 0, "missed_cycles": 0}


def test_one_latency_summary_in_microseconds_for_lists_and_kept_arrays():
    values = [1e-4] * 999 + [1e-3]
    s = latency_summary(values)
    assert list(s) == ["count", "p50_us", "p90_us", "p99_us", "p999_us", "max_us"]
    assert s["count"] == 1000 and s["p50_us"] == pytest.approx(100.0) and s["max_us"] == pytest.approx(1000.0)
    assert 100.0 <= s["p999_us"] <= 1000.0
    t = TickTiming(keep_all=True)
    for v in values:
        t.tick(0.0, v, False)
    assert latency_summary(t.latency) == s  # the kept array.array reads the same
    assert latency_summary([]) == {"count": 0, "p50_us": 0.0, "p90_us": 0.0, "p99_us": 0.0, "p999_us": 0.0,
                                   "max_us": 0.0}
