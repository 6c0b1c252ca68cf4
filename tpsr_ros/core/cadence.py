"""Messages missing from a steady stream, counted from the gaps in its header stamps.

Why: the middleware does not always say what it lost. Cyclone DDS raises no status for
samples that a keep-last writer dropped before a slow or stalled reader had them, and a
camera driver may drop frames before publishing. A sensor publishing at a steady rate
stamps its messages one period apart, so a stamp n periods after the previous one means
n - 1 messages went missing somewhere between the sensor and the receiver, whoever lost
them. But a long interval is not always a loss: a phone's camera stretches a frame now
and then (2 or 3 periods, a frame counter without a gap), and stamps alone cannot tell
one such frame from a lost one. The rule weighs the stream's own evidence:

- a stream whose recent intervals all stay near one period (a camera, odometry) loses a
  message where an interval is an integer multiple of that period, within the stream's
  own jitter: a lost frame keeps the phase, a stretched one rarely does;
- once a stream shows a stretched frame (an interval past the regular band that is no
  such multiple), only intervals longer than its longest recent frames plus 1.5 periods
  are losses, and the counts it gave to shorter ones are taken back;
- streams with no steady core (commands sent on events, two publishers interleaved on
  one topic) are not judged.

It learns everything from the stream itself, so it needs no configuration.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

__all__ = ["CadenceGaps"]

HISTORY = 256
"""Intervals remembered for the longest frame a stream has shown (its stretch envelope)."""
STEADY_CORE_INTERVALS = 32
"""Intervals needed to judge a stream by its lower quartile (fewer: all must be regular)."""
BEYOND_LONGEST = 1.5
"""A stretching stream's interval is a loss only past its longest frames plus this many periods."""


@dataclass
class CadenceGaps:
    """Counts stamps missing from one stream's cadence; feed it with :meth:`add`.

    ``window`` intervals estimate the period: their median, or their mean when they all lie
    within ``tolerance`` (relative) of it (a regular stream: the stamps' jitter then cancels,
    which makes the count exact for gaps of a few dozen periods). The stream is judged once
    ``min_intervals`` are known and all lie within ``tolerance`` of the median, or once
    :data:`STEADY_CORE_INTERVALS` are known and their lower quartile does (a steady core;
    a third of stretched frames keeps one).

    What it counts, and what it cannot see:

    - A regular stream (no interval of the last :data:`HISTORY` beyond ``1 + tolerance``
      periods): an interval within the stream's jitter of n >= 2 periods is n - 1 lost,
      exactly. Any other long interval is a stretched frame, and the stream is stretching
      from then on.
    - A stretching stream (a phone's camera, or jitter beyond ``tolerance``): an interval
      longer than its longest frame of the last :data:`HISTORY` plus
      :data:`BEYOND_LONGEST` periods is a loss, of as many messages as the stream's mean
      interval fits in it, less one (an estimate). Shorter losses, such as a single frame
      dropped by a phone that stretches frames to 3 periods, cannot be told from a
      stretched frame and are not counted: the count is a lower bound.
    - A stream's first long frame comes before it has shown what it stretches to: in a
      regular stream a frame stretched to an exact multiple of the period reads as a loss,
      and so does, in a jittery one, a frame longer than its jitter plus 1.5 periods. The
      count is taken back (``missing`` goes down) when a later long frame shows the stream
      stretches that far, so a complete recording that shows its long frames more than
      once counts none; one whose only long frame is such a frame counts it.

    A backward jump of the stamps (a restarted sensor, a bag replayed in a loop) starts
    afresh; equal stamps are ignored. :meth:`skip` names stamps left out on purpose.
    """

    window: int = 64
    min_intervals: int = 8
    tolerance: float = 0.25
    missing: int = 0
    gaps: int = 0
    period_ns: float | None = field(default=None, init=False)
    _last: int | None = field(default=None, init=False, repr=False)
    _intervals: deque[float] = field(init=False, repr=False)
    _history: deque[tuple[int, float]] = field(init=False, repr=False)  # (end stamp, interval)
    _since_estimate: int = field(default=0, init=False, repr=False)
    _mean_ns: float = field(default=0.0, init=False, repr=False)
    _median_ns: float = field(default=0.0, init=False, repr=False)
    _jitter: float = field(default=0.0, init=False, repr=False)
    _longest_ns: float = field(default=0.0, init=False, repr=False)
    _skips: deque[int] = field(init=False, repr=False)
    _gaps: deque[list[int]] = field(init=False, repr=False)  # [start, end, lost, interval]

    def __post_init__(self) -> None:
        self._intervals = deque(maxlen=self.window)
        self._history = deque(maxlen=HISTORY)
        self._skips = deque(maxlen=16)
        self._gaps = deque(maxlen=64)

    @property
    def stretching(self) -> bool:
        """Whether the stream showed a frame beyond the regular band lately (see the class)."""
        return self._median_ns > 0 and self._longest_ns > (1 + self.tolerance) * self._median_ns

    def skip(self, stamp_ns: int) -> None:
        """A stamp the stream leaves out on purpose (a simulator's reset takes a step's
        stamp): not a loss, whether it is told before or after the messages that follow it."""
        stamp_ns = int(stamp_ns)
        if self._last is not None and stamp_ns < self._last:  # told late
            for gap in self._gaps:
                if gap[0] < stamp_ns < gap[1] and gap[2] > 0:  # counted: take it back
                    self._take_back(gap, 1)
                    return
            return
        self._skips.append(stamp_ns)

    def add(self, stamp_ns: int) -> int:
        """The next message's stamp; returns how many messages are missing just before it
        (a count later taken back lowers :attr:`missing`, not this return value)."""
        last, self._last = self._last, stamp_ns
        if last is None:
            return 0
        interval = stamp_ns - last
        if interval <= 0:
            if interval < 0:  # time went back: a new stream
                self._restart()
            else:
                self._last = last
            return 0
        skipped = sum(1 for s in self._skips if last < s < stamp_ns)
        lost = self._judge(interval, skipped) if self.period_ns is not None else 0
        if lost:
            self.missing += lost
            self.gaps += 1
            self._gaps.append([last, stamp_ns, lost, interval])
            self._intervals.append(interval / (lost + skipped + 1))
        else:
            per_message = interval / (skipped + 1)
            self._intervals.append(per_message)
            stretched = self.period_ns is not None and self.stretching
            self._remember(stamp_ns, per_message)
            if self.period_ns is not None and (stretched or self.stretching):
                self._take_back_within_envelope()
        self._since_estimate += 1
        if self._since_estimate >= self.min_intervals or (
            self.period_ns is None and len(self._intervals) >= self.min_intervals
        ):
            self._estimate()
        return lost

    def _judge(self, interval: float, skipped: int) -> int:
        """Messages lost in ``interval`` (0: a regular or a stretched frame)."""
        period = float(self.period_ns or 0)
        ratio = interval / period
        if ratio < 1.5:
            return 0
        if not self.stretching:
            n = round(ratio)
            # a lost frame keeps the phase: within the stream's jitter of a multiple (and the
            # period's error, which grows with the multiple)
            allowed = min(0.4, max(0.1, 2 * self._jitter)) + n * self._jitter / len(self._intervals)
            if abs(ratio - n) <= allowed:
                return max(0, n - 1 - skipped)
            return 0  # stretched: the stream is stretching from now on
        if interval <= self._envelope():
            return 0
        return max(1, round(interval / self._mean_ns) - 1 - skipped)

    def _remember(self, stamp_ns: int, interval: float) -> None:
        """An interval that was no loss, for the stream's longest frames."""
        evicted = self._history[0][1] if len(self._history) == self._history.maxlen else None
        self._history.append((stamp_ns, interval))
        if evicted is not None and evicted >= self._longest_ns:
            self._longest_ns = max(i for _, i in self._history)
        else:
            self._longest_ns = max(self._longest_ns, interval)

    def _envelope(self) -> float:
        """The longest interval a stretching stream may show without a loss (ns)."""
        return self._longest_ns + BEYOND_LONGEST * self._median_ns

    def _take_back_within_envelope(self) -> None:
        """Counts given to intervals a stretching stream now shows it can stretch to."""
        since = self._history[0][0] - self._history[0][1]
        envelope = self._envelope()
        for gap in self._gaps:
            if gap[2] > 0 and gap[1] >= since and gap[3] <= envelope:
                self._take_back(gap, gap[2])

    def _take_back(self, gap: list[int], count: int) -> None:
        gap[2] -= count
        self.missing -= count
        self.gaps -= int(gap[2] == 0)

    def _restart(self) -> None:
        self._intervals.clear()
        self._history.clear()
        self._gaps.clear()
        self.period_ns = None
        self._median_ns = self._mean_ns = self._jitter = self._longest_ns = 0.0
        self._since_estimate = 0

    def _estimate(self) -> None:
        """The period from the window, or None when the stream has no steady core."""
        self._since_estimate = 0
        if len(self._intervals) < self.min_intervals:
            self.period_ns = None
            return
        ordered = sorted(self._intervals)
        n = len(ordered)
        median = ordered[n // 2]
        jitter = max(median - ordered[0], ordered[-1] - median) / median
        steady_core = n >= STEADY_CORE_INTERVALS and ordered[n // 4] >= (1 - self.tolerance) * median
        if jitter > self.tolerance and not steady_core:
            self.period_ns = None  # no steady core: events, or two streams interleaved
            return
        self._median_ns, self._mean_ns, self._jitter = median, sum(ordered) / n, jitter
        # the mean of regular intervals is the span of their stamps over their count: the
        # stamps' jitter cancels, which a long gap (n periods) needs to round to n
        self.period_ns = self._mean_ns if self._jitter <= self.tolerance else median
