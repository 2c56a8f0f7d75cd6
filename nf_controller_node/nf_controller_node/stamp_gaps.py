"""Joint states that never reached the controller, counted from the stamps of those that did.

A control loop reads its joint states keep-last (the newest matters): when its executor stalls for
longer than the reader's depth of states, newer ones overwrite older ones unread, and DDS says
nothing. A driver that stamps every state with its control clock (the sim's simulated time,
libfranka's robot time) leaves a hole in the stamps instead: a gap of more than 1.5 control periods
between two states received in order holds round(gap / period) - 1 states that did not arrive.

Equal stamps (a lockstep sim's resends, the state a reset leaves) and older ones (rejected as out
of order by the loop) count nothing and do not move the reference. A forward jump of more than
``max_gap`` is a change of time base, counted as a jump, not as millions of missing states. With
wall-clock stamps, jitter of more than half a period would count as gaps: use the control clock.
"""

from __future__ import annotations

MAX_GAP = 1.0  # s: a longer forward step of the stamps is a jump of the time base


class StampGaps:
    """Counts the states missing between received ones (``missing``), the gaps they sat in (``gaps``)
    and forward jumps of the stamps (``jumps``)."""

    def __init__(self, period: float, max_gap: float = MAX_GAP) -> None:
        """``period``: s between the driver's states (0: count nothing); ``max_gap``: s, see module."""
        if not period >= 0.0:
            raise ValueError(f"period must be >= 0 s, got {period}")
        if not max_gap > period:
            raise ValueError(f"max_gap must be > period ({period} s), got {max_gap}")
        self.period_ns = round(period * 1e9)
        self.max_gap_ns = round(max_gap * 1e9)
        self.missing = 0
        self.gaps = 0
        self.jumps = 0
        self._last = -1  # ns, newest stamp received (-1: none yet)

    def observe(self, stamp_ns: int) -> int:
        """One received state's stamp (ns); returns the number of states missing just before it."""
        last = self._last
        if stamp_ns <= last:
            return 0
        self._last = stamp_ns
        if last < 0 or self.period_ns == 0:
            return 0
        gap = stamp_ns - last
        if gap > self.max_gap_ns:
            self.jumps += 1
            return 0
        if 2 * gap <= 3 * self.period_ns:  # within 1.5 periods
            return 0
        missing = max(round(gap / self.period_ns) - 1, 1)
        self.missing += missing
        self.gaps += 1
        return missing

    def restart(self) -> None:
        """Forget the reference stamp (the driver restarted its clock); the counts stay."""
        self._last = -1
