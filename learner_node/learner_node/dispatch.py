"""The rollouts of one batch (an iteration, an evaluation) handed out to many arms. ROS-free.

A ``WorkQueue`` holds rollout indices pending, in flight (with the arm and the dispatch that runs
them) and done. Every dispatch gets a ``Ticket`` whose ``number`` grows with each dispatch of the
batch (so a policy version derived from it only grows on every arm, a re-run included). A rollout
whose arm was lost, or whose episode failed, goes back to the queue and runs again with the same
index (so the same seeds), on whichever arm asks next; a result is accepted only from the ticket
that currently holds the rollout, so a re-queued rollout's late answer is never counted twice.
"""

from __future__ import annotations

import heapq
import threading
from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Generic, TypeVar

T = TypeVar("T")


class Outcome(StrEnum):
    """What became of one dispatch."""

    DONE = "done"  # its result counts
    FAILED = "failed"  # the episode failed or arrived incomplete: costs an attempt
    HOLD = "hold"  # the arm was in safe hold (a latched fault): free up to ``max_holds`` times
    LOST = "lost"  # the arm died or disconnected mid-episode: free up to ``max_losses`` times
    LATE = "late"  # a result from a ticket that no longer held its rollout: ignored


@dataclass(frozen=True)
class Ticket:
    """One dispatch: rollout ``index`` of the batch on ``arm``, the batch's ``number``-th dispatch."""

    index: int
    number: int
    arm: str


@dataclass
class _Rollout:
    attempts: int = 0  # FAILED dispatches
    holds: int = 0
    losses: int = 0
    ticket: Ticket | None = None  # the dispatch holding it now


@dataclass
class Dispatch:
    """A ticket and its outcome (None while in flight), in the order they were handed out."""

    ticket: Ticket
    outcome: Outcome | None = None
    reason: str = ""
    late: bool = False  # its result came after the rollout was re-queued or done elsewhere (ignored)


@dataclass
class WorkQueue(Generic[T]):
    """``size`` rollouts to run once each. ``retries``: failed attempts a rollout may repeat before it
    is dropped; ``max_holds``/``max_losses``: safe holds and lost arms a rollout may meet before
    they count as failed attempts too (an episode that faults or crashes every arm it runs on)."""

    size: int
    retries: int = 2
    max_holds: int = 3
    max_losses: int = 3
    dispatches: list[Dispatch] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self._pending = list(range(self.size))  # a heap: the lowest index first, re-queued ones too
        self._rollouts = [_Rollout() for _ in range(self.size)]
        self._results: dict[int, T] = {}
        self._dropped: set[int] = set()
        self._by_number: dict[int, Dispatch] = {}
        self._closed = False
        self._changed = threading.Condition()

    # ------------------------------------------------------------------ arms' side
    def take(self, arm: str) -> Ticket | None:
        """The next pending rollout for ``arm`` (now in flight), or None when none is pending."""
        with self._changed:
            if self._closed or not self._pending:
                return None
            index = heapq.heappop(self._pending)
            ticket = Ticket(index, len(self.dispatches), arm)
            self._rollouts[index].ticket = ticket
            entry = Dispatch(ticket)
            self.dispatches.append(entry)
            self._by_number[ticket.number] = entry
            return ticket

    def finish(self, ticket: Ticket, result: T) -> bool:
        """Record ``ticket``'s result; False (ignored, logged as LATE) if the ticket no longer holds its rollout."""
        with self._changed:
            if not self._holds(ticket):
                self._close_entry(ticket, Outcome.LATE, "its rollout was re-queued or is done")
                return False
            self._results[ticket.index] = result
            self._rollouts[ticket.index].ticket = None
            self._close_entry(ticket, Outcome.DONE)
            self._changed.notify_all()
            return True

    def fail(self, ticket: Ticket, outcome: Outcome, reason: str = "") -> bool:
        """``ticket`` did not deliver (FAILED, HOLD or LOST): its rollout is re-queued (True) or, out of
        attempts, dropped (False). Ignored (False) if the ticket no longer holds its rollout."""
        if outcome not in (Outcome.FAILED, Outcome.HOLD, Outcome.LOST):
            raise ValueError(f"not a failure: {outcome}")
        with self._changed:
            if not self._holds(ticket):
                self._close_entry(ticket, Outcome.LATE, reason)
                return False
            r = self._rollouts[ticket.index]
            r.ticket = None
            self._close_entry(ticket, outcome, reason)
            if outcome is Outcome.HOLD:
                r.holds += 1
            elif outcome is Outcome.LOST:
                r.losses += 1
            if outcome is Outcome.FAILED or r.holds > self.max_holds or r.losses > self.max_losses:
                r.attempts += 1
            requeue = r.attempts <= self.retries
            if requeue:
                heapq.heappush(self._pending, ticket.index)
            else:
                self._dropped.add(ticket.index)
            self._changed.notify_all()
            return requeue

    def lose_arm(self, arm: str, reason: str = "arm lost") -> list[int]:
        """Every rollout in flight on ``arm`` goes back to the queue (LOST); their indices."""
        with self._changed:
            held = [r.ticket for r in self._rollouts if r.ticket is not None and r.ticket.arm == arm]
        return [t.index for t in held if self.fail(t, Outcome.LOST, reason)]

    # ------------------------------------------------------------------ the learner's side
    @property
    def complete(self) -> bool:
        """Every rollout is done or dropped."""
        with self._changed:
            return len(self._results) + len(self._dropped) == self.size

    def has_pending(self) -> bool:
        """A rollout waits for an arm."""
        with self._changed:
            return bool(self._pending) and not self._closed

    def in_flight(self) -> dict[int, Ticket]:
        """Rollouts being run, by index."""
        with self._changed:
            return {i: r.ticket for i, r in enumerate(self._rollouts) if r.ticket is not None}

    def wait(self, timeout: float, for_work: bool = False) -> bool:
        """Block up to ``timeout`` s until the batch is complete (or, ``for_work``, a rollout is pending
        too); True if so."""
        def ready() -> bool:
            done = len(self._results) + len(self._dropped) == self.size or self._closed
            return done or (for_work and bool(self._pending))

        with self._changed:
            return self._changed.wait_for(ready, timeout)

    def close(self) -> None:
        """Hand out nothing more (the learner stops); waiters wake up."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    def results(self) -> list[T | None]:
        """Each rollout's result in index order, None for a dropped one."""
        with self._changed:
            return [self._results.get(i) for i in range(self.size)]

    @property
    def dropped(self) -> list[int]:
        """Indices of the rollouts dropped after all their attempts."""
        with self._changed:
            return sorted(self._dropped)

    def ran_on(self) -> list[str | None]:
        """The arm whose result counts for each rollout (None: dropped or not done)."""
        with self._changed:
            arm: list[str | None] = [None] * self.size
            for d in self.dispatches:
                if d.outcome is Outcome.DONE:
                    arm[d.ticket.index] = d.ticket.arm
            return arm

    def arm_counts(self) -> dict[str, dict[str, int]]:
        """Per arm: its dispatches by outcome (``in_flight`` for those still running)."""
        with self._changed:
            out: dict[str, Counter[str]] = {}
            for d in self.dispatches:
                key = d.outcome.value if d.outcome is not None else "in_flight"
                counts = out.setdefault(d.ticket.arm, Counter())
                counts[key] += 1
                if d.late:
                    counts[Outcome.LATE.value] += 1
            return {arm: dict(c) for arm, c in out.items()}

    # ------------------------------------------------------------------ internals
    def _holds(self, ticket: Ticket) -> bool:
        return self._rollouts[ticket.index].ticket == ticket

    def _close_entry(self, ticket: Ticket, outcome: Outcome, reason: str = "") -> None:
        entry = self._by_number.get(ticket.number)
        if entry is None:
            return
        if outcome is Outcome.LATE:
            entry.late = True
        elif entry.outcome is None:
            entry.outcome, entry.reason = outcome, reason
