"""Messages missing from a steady stream, counted from the gaps in its header stamps.

Why: the middleware does not always say what it lost. Cyclone DDS raises no status for
samples that a keep-last writer dropped before a slow or stalled reader had them, and a
camera driver may drop frames before publishing. A sensor publishing at a steady rate
stamps its messages one period apart, so a stamp n periods after the previous one means
n - 1 messages went missing somewhere between the sensor and the receiver, whoever lost
them. The rule judges only streams whose recent cadence is regular (a camera, odometry;
not commands sent on events, nor two publishers interleaved on one topic), and learns the
period from the stream itself (the median of the last intervals), so it needs no
configuration.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

__all__ = ["CadenceGaps"]


@dataclass
class CadenceGaps:
    """Counts stamps missing from one stream's regular cadence; feed it with :meth:`add`.

    ``window`` intervals estimate the period; the cadence is regular when at least
    ``min_intervals`` are known and every interval of the window lies within ``tolerance``
    (relative) of their median: a stream is judged against its own jitter, so a camera whose
    intervals vary by more (a phone's stretched frames) is never read as losing messages.
    The period is then the window's mean, which makes
    the count exact for gaps of a few dozen periods with a jitter of 10 % of a period
    (longer gaps are counted to within the period's error times their length). A backward
    jump of the stamps (a restarted sensor, a bag replayed in a loop) starts the estimate
    afresh; equal stamps are ignored.
    """

    window: int = 32
    min_intervals: int = 8
    tolerance: float = 0.25
    missing: int = 0
    gaps: int = 0
    period_ns: float | None = field(default=None, init=False)
    _last: int | None = field(default=None, init=False, repr=False)
    _intervals: deque[float] = field(init=False, repr=False)
    _since_estimate: int = field(default=0, init=False, repr=False)
    _skips: deque[int] = field(init=False, repr=False)
    _gaps: deque[list[int]] = field(init=False, repr=False)  # [start, end, lost] of gaps

    def __post_init__(self) -> None:
        self._intervals = deque(maxlen=self.window)
        self._skips = deque(maxlen=16)
        self._gaps = deque(maxlen=16)

    def skip(self, stamp_ns: int) -> None:
        """A stamp the stream leaves out on purpose (a simulator's reset takes a step's
        stamp): not a loss, whether it is told before or after the messages that follow it."""
        stamp_ns = int(stamp_ns)
        if self._last is not None and stamp_ns < self._last:  # told late
            for gap in self._gaps:
                if gap[0] < stamp_ns < gap[1] and gap[2] > 0:  # counted: take it back
                    gap[2] -= 1
                    self.missing -= 1
                    self.gaps -= int(gap[2] == 0)
                    return
            return
        self._skips.append(stamp_ns)

    def add(self, stamp_ns: int) -> int:
        """The next message's stamp; returns how many messages are missing just before it."""
        last, self._last = self._last, stamp_ns
        if last is None:
            return 0
        interval = stamp_ns - last
        if interval <= 0:
            if interval < 0:  # time went back: a new stream
                self._intervals.clear()
                self.period_ns = None
            else:
                self._last = last
            return 0
        lost = 0
        period = self.period_ns
        skipped = sum(1 for s in self._skips if last < s < stamp_ns)
        if period is not None and interval >= 1.5 * period:
            periods = round(interval / period)
            lost = max(0, periods - 1 - skipped)
            self.missing += lost
            self.gaps += int(lost > 0)
            interval /= periods
        elif skipped:  # the cadence is not known yet: the skipped stamps stand in
            interval /= skipped + 1
        if lost:
            self._gaps.append([last, stamp_ns, lost])
        self._intervals.append(interval)
        self._since_estimate += 1
        if self._since_estimate >= self.min_intervals or (
            period is None and len(self._intervals) >= self.min_intervals
        ):
            self._estimate()
        return lost

    def _estimate(self) -> None:
        """The period from the window, or None when the cadence is not regular."""
        self._since_estimate = 0
        if len(self._intervals) < self.min_intervals:
            self.period_ns = None
            return
        ordered = sorted(self._intervals)
        n = len(ordered)
        median = ordered[n // 2]
        low, high = ordered[0], ordered[-1]
        regular = (1 - self.tolerance) * median <= low and high <= (1 + self.tolerance) * median
        # the mean of regular intervals is the span of their stamps over their count: the
        # stamps' jitter cancels, which a long gap (n periods) needs to round to n
        self.period_ns = sum(ordered) / n if regular else None
