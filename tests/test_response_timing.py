"""ResponseTiming: latency from a published state to its answer, deadline misses and runs."""

import pytest

from sim_bridge_node.response_timing import ResponseTiming


def test_latency_is_time_from_state_to_its_answer():
    t = ResponseTiming(keep_all=True)
    t.published(1000, 10.0)
    assert t.answered(1000, 10.0003) == pytest.approx(3e-4)
    assert t.answered(1000, 10.0004) is None  # a second answer to the same state is not counted
    assert t.answered(999, 10.0005) is None  # unknown state
    assert list(t.all) == pytest.approx([3e-4])
    assert t.counters()["answers"] == 1


def test_misses_count_only_after_the_first_answer_and_runs_are_tracked():
    t = ResponseTiming()
    for k in range(5):  # nobody answers yet: the driver holds, no misses counted
        t.published(k, k * 1e-3)
    assert t.misses == 0
    t.answered(4, 4.2e-3)
    # states 5..7 unanswered, 8 answered late (after 9 went out), 9 answered in time
    for k in range(5, 10):
        t.published(k, k * 1e-3)
    t.answered(8, 9.5e-3)
    t.answered(9, 9.6e-3)
    t.published(10, 10e-3)
    t.published(11, 11e-3)  # state 10 unanswered: a run of 1
    c = t.counters()
    assert c["deadline_misses"] == 5  # 5, 6, 7, 8, 10
    assert c["longest_miss_run"] == 4  # 5..8
    assert c["late_answers"] == 1
    assert t.run == 1
    assert t.long_runs == []  # runs shorter than LONG_RUN are not kept


def test_long_runs_are_kept_with_their_time():
    t = ResponseTiming()
    t.published(0, 0.0)
    t.answered(0, 0.0002)
    for k in range(1, 9):  # states 1..7 unanswered: a run of 7 starting at state 2's tick
        t.published(k, k * 1e-3)
    t.answered(8, 8.3e-3)
    t.published(9, 9e-3)
    assert t.long_runs == [(pytest.approx(2e-3 - 2e-4), 7)]


def test_window_is_taken_and_reset():
    t = ResponseTiming()
    t.published(1, 0.0)
    t.answered(1, 2e-4)
    assert t.take_window() == pytest.approx([2e-4])
    assert t.take_window() == []
    assert t.all is None

