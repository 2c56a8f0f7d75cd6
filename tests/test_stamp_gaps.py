"""StampGaps: joint states that never reached the standalone controller, counted from the holes in
the stamps of those that did (the keep-last reader's overwrites are not reported by DDS)."""

from __future__ import annotations

import pytest

from nf_controller_node.stamp_gaps import StampGaps

MS = 1_000_000


def _feed(gaps: StampGaps, stamps) -> list[int]:
    return [gaps.observe(s) for s in stamps]


def test_consecutive_states_count_nothing():
    gaps = StampGaps(0.001)
    assert _feed(gaps, [k * MS for k in range(1, 200)]) == [0] * 199
    assert (gaps.missing, gaps.gaps, gaps.jumps) == (0, 0, 0)


def test_holes_count_the_states_in_them():
    gaps = StampGaps(0.001)
    received = [1, 2, 3, 7, 8, 10, 20]  # missing: 4-6, 9, 11-19
    out = _feed(gaps, [k * MS for k in received])
    assert out == [0, 0, 0, 3, 0, 1, 9]
    assert (gaps.missing, gaps.gaps) == (13, 3)


def test_jitter_under_half_a_period_is_not_a_gap():
    gaps = StampGaps(0.001)
    _feed(gaps, [1 * MS, int(2.4 * MS), int(3.6 * MS), int(4.5 * MS)])
    assert gaps.missing == 0


def test_resends_and_out_of_order_states_neither_count_nor_move_the_reference():
    gaps = StampGaps(0.001)
    out = _feed(gaps, [5 * MS, 5 * MS, 5 * MS, 2 * MS, 6 * MS])  # lockstep resends, one old stamp
    assert out == [0] * 5 and gaps.missing == 0


def test_a_jump_of_the_time_base_is_not_millions_of_missing_states():
    gaps = StampGaps(0.001)
    far = (2**31 - 1) * 1_000_000_000
    _feed(gaps, [1 * MS, 2 * MS, far, 3 * MS, 4 * MS])
    assert (gaps.missing, gaps.jumps) == (0, 1)
    gaps.restart()  # clear_fault: the driver's clock is the time base again
    _feed(gaps, [5 * MS, 8 * MS])
    assert gaps.missing == 2


def test_period_zero_counts_nothing_and_bad_settings_are_refused():
    gaps = StampGaps(0.0)
    _feed(gaps, [1 * MS, 50 * MS])
    assert gaps.missing == 0
    with pytest.raises(ValueError, match="period"):
        StampGaps(-0.001)
    with pytest.raises(ValueError, match="max_gap"):
        StampGaps(0.001, max_gap=0.001)
