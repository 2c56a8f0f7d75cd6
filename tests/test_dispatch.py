"""The learner's work queue (``learner_node.dispatch``): rollouts handed to many arms, re-queued on a
lost arm or a failed episode with the same index, never counted twice, in index order at the end."""

from __future__ import annotations

import threading

from learner_node.dispatch import Outcome, WorkQueue


def test_every_rollout_once_in_index_order_whatever_arm_ran_it():
    q: WorkQueue[str] = WorkQueue(4)
    a, b = q.take("/a"), q.take("/b")
    c = q.take("/a")
    assert (a.index, b.index, c.index) == (0, 1, 2) and [a.number, b.number, c.number] == [0, 1, 2]
    assert q.finish(c, "r2") and q.finish(a, "r0") and q.finish(b, "r1")
    d = q.take("/b")
    assert q.take("/a") is None and not q.complete
    assert q.finish(d, "r3") and q.complete
    assert q.results() == ["r0", "r1", "r2", "r3"]
    assert q.ran_on() == ["/a", "/b", "/a", "/b"]
    assert q.arm_counts() == {"/a": {"done": 2}, "/b": {"done": 2}}


def test_a_lost_arm_requeues_its_rollout_first_and_its_late_result_is_ignored():
    q: WorkQueue[str] = WorkQueue(3)
    t0, t1 = q.take("/dead"), q.take("/ok")
    assert q.lose_arm("/dead") == [0]
    assert q.in_flight() == {1: t1}
    again = q.take("/ok2")
    assert again.index == 0 and again.number == 2  # the re-run comes first, with a larger dispatch number
    assert not q.finish(t0, "stale")  # the dead arm's answer arrives after all: not counted
    assert q.finish(again, "r0") and q.finish(t1, "r1")
    assert not q.finish(t0, "stale again")
    t2 = q.take("/ok")
    assert q.finish(t2, "r2") and q.complete
    assert q.results() == ["r0", "r1", "r2"]
    assert q.arm_counts()["/dead"] == {"lost": 1, "late": 1}
    assert [d.outcome for d in q.dispatches] == [Outcome.LOST, Outcome.DONE, Outcome.DONE, Outcome.DONE]


def test_failed_attempts_are_retried_then_dropped():
    q: WorkQueue[str] = WorkQueue(2, retries=1)
    t = q.take("/a")
    assert q.fail(t, Outcome.FAILED, "incomplete")  # attempt 1: again
    t = q.take("/b")
    assert t.index == 0 and not q.fail(t, Outcome.FAILED, "incomplete")  # attempt 2: dropped
    assert q.dropped == [0]
    t = q.take("/a")
    assert t.index == 1 and q.finish(t, "r1") and q.complete
    assert q.results() == [None, "r1"] and q.ran_on() == [None, "/a"]


def test_holds_and_losses_are_free_up_to_their_limit():
    q: WorkQueue[str] = WorkQueue(1, retries=0, max_holds=2, max_losses=1)
    for _ in range(2):
        assert q.fail(q.take("/a"), Outcome.HOLD)
    assert q.fail(q.take("/b"), Outcome.LOST)
    assert not q.fail(q.take("/c"), Outcome.LOST)  # the second loss counts: no retries left
    assert q.complete and q.results() == [None]


def test_a_failure_reported_after_the_rollout_moved_on_changes_nothing():
    q: WorkQueue[str] = WorkQueue(1)
    t = q.take("/a")
    q.lose_arm("/a")
    t2 = q.take("/b")
    assert not q.fail(t, Outcome.FAILED)  # the old ticket: ignored, nothing re-queued
    assert not q.has_pending() and q.in_flight() == {0: t2}
    assert q.finish(t2, "r") and q.results() == ["r"]


def test_arms_in_threads_take_everything_exactly_once():
    n = 200
    q: WorkQueue[int] = WorkQueue(n)
    seen: list[int] = []
    lock = threading.Lock()

    def arm(name: str) -> None:
        while (t := q.take(name)) is not None:
            if t.number % 7 == 3:  # some dispatches fail and come back
                q.fail(t, Outcome.LOST)
                continue
            with lock:
                seen.append(t.index)
            q.finish(t, t.index)

    threads = [threading.Thread(target=arm, args=(f"/arm{i}",)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert q.wait(1.0) and sorted(seen) == list(range(n)) and q.results() == list(range(n))


def test_wait_wakes_on_work_and_on_close():
    q: WorkQueue[int] = WorkQueue(1)
    t = q.take("/a")
    assert not q.wait(0.01, for_work=True)
    threading.Timer(0.05, lambda: q.lose_arm("/a")).start()
    assert q.wait(5.0, for_work=True) and q.has_pending()
    q.close()
    assert q.take("/b") is None and q.wait(0.01)
    assert t.index == 0
