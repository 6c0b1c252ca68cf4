"""The filter node's health without ROS: counters, input rates, warning throttles, the verdict.

:class:`HealthLedger` keeps what ``/diagnostics`` reports: rejected messages by reason,
arrivals of each input (rates over the last :data:`RATE_WINDOW_S`, time since the last),
runs of filter recoveries, and the counters of the previous report, against which
:meth:`HealthLedger.assess` judges what got worse. :class:`Throttle` lets a warning through
at most once per key and period. Levels are those of ``diagnostic_msgs/DiagnosticStatus``.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from tpsr_ros.filter_node.inputs import REJECT_REASONS

__all__ = [
    "ERROR",
    "INPUTS",
    "MIN_SHARE_SAMPLES",
    "OK",
    "RATE_WINDOW_S",
    "STALE",
    "WARN",
    "HealthLedger",
    "Throttle",
]

OK, WARN, ERROR, STALE = 0, 1, 2, 3
"""``diagnostic_msgs/msg/DiagnosticStatus`` levels."""

INPUTS = ("image", "action")
RATE_WINDOW_S = 10.0
"""Input rates count the messages of the last this many seconds."""
RECOVERY_ERROR_RUN = 10
"""This many consecutive updates that all needed recovery are an ERROR."""
MIN_SHARE_SAMPLES = 20
"""A share (``far_commands_warn``) is judged over at least this many messages: a report
with fewer since the last judged one judges nothing and carries them to the next."""

Clock = Callable[[], float]


class Throttle:
    """True at most once per key every ``period_s`` (by ``clock``); counts what it held back."""

    def __init__(self, period_s: float, clock: Clock = time.monotonic) -> None:
        self.period_s = period_s
        self._clock = clock
        self._last: dict[tuple[str, str], float] = {}
        self.suppressed: dict[tuple[str, str], int] = {}

    def __call__(self, key: tuple[str, str]) -> bool:
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return False
        self._last[key] = now
        return True

    def take_suppressed(self, key: tuple[str, str]) -> int:
        """How many warnings of ``key`` were held back since the last one let through."""
        return self.suppressed.pop(key, 0)

    def warning(self, key: tuple[str, str], message: str) -> str | None:
        """``message`` (with how many were held back since the last) if one of ``key`` may
        be logged now, else None."""
        if not self(key):
            return None
        held = self.take_suppressed(key)
        return message + (f" ({held} more since the last warning)" if held else "")


class HealthLedger:
    """What the node's ``/diagnostics`` report says, kept without ROS.

    ``input_timeout_s``: an input silent for longer is a WARN, both silent STALE.
    """

    def __init__(self, input_timeout_s: float, clock: Clock = time.monotonic) -> None:
        self.input_timeout_s = input_timeout_s
        self.clock = clock
        self.rejected = dict.fromkeys(REJECT_REASONS, 0)
        self.recovery_run = 0
        self._arrivals: dict[str, deque[float]] = {k: deque(maxlen=100_000) for k in INPUTS}
        self._last_arrival: dict[str, float | None] = dict.fromkeys(INPUTS)
        self._reported: tuple[float, int, dict[str, int]] = (clock(), 0, {})

    # -- events ------------------------------------------------------------------------

    def arrived(self, which: str) -> None:
        """An input message arrived (``which``: ``image`` or ``action``)."""
        now = self.clock()
        self._last_arrival[which] = now
        arrivals = self._arrivals[which]
        arrivals.append(now)
        while arrivals[0] < now - RATE_WINDOW_S:
            arrivals.popleft()

    def reject(self, reason: str) -> None:
        """A message was rejected for ``reason`` (one of :data:`REJECT_REASONS`)."""
        self.rejected[reason] += 1

    def update(self, recovered: bool) -> None:
        """A filter update happened; ``recovered``: its normaliser needed the guard."""
        self.recovery_run = self.recovery_run + 1 if recovered else 0

    # -- reports -------------------------------------------------------------------------

    def input_values(self, topics: Mapping[str, str]) -> dict[str, Any]:
        """Rate, age and topic of each input (``topics``: input -> topic name)."""
        now = self.clock()
        values: dict[str, Any] = {}
        for which in INPUTS:
            recent = [t for t in self._arrivals[which] if t >= now - RATE_WINDOW_S]
            span = min(RATE_WINDOW_S, now - recent[0]) if len(recent) > 1 else 0.0
            values[f"{which}_rate_hz"] = (len(recent) - 1) / span if span > 0 else 0.0
            last = self._last_arrival[which]
            values[f"{which}_age_s"] = "never" if last is None else round(now - last, 3)
            values[f"{which}_topic"] = topics[which]
        return values

    def idle_for(self) -> float | None:
        """Seconds since any input last arrived (None before the first)."""
        arrivals = [t for t in self._last_arrival.values() if t is not None]
        return self.clock() - max(arrivals) if arrivals else None

    def silent(self) -> list[tuple[str, float]]:
        """Inputs that delivered before but nothing for longer than the timeout, with ages."""
        now = self.clock()
        return [
            (which, now - last)
            for which in INPUTS
            if (last := self._last_arrival[which]) is not None and now - last > self.input_timeout_s
        ]

    def update_rate(self, steps: int) -> float:
        """Updates per second since the last report."""
        since, steps_then, _ = self._reported
        return (steps - steps_then) / max(self.clock() - since, 1e-9)

    def assess(
        self, counts: Mapping[str, int], steps: int, topics: Mapping[str, str]
    ) -> tuple[int, str]:
        """Level and message of a report: what got worse since the previous report.

        ``counts`` are the problem counters (growing totals), ``steps`` the updates so far.
        """
        _, steps_then, counts_then = self._reported
        grown = [k for k, v in counts.items() if v > counts_then.get(k, 0)]
        rejected_now = sum(
            v - counts_then.get(k, 0) for k, v in counts.items() if k.startswith("rejected_")
        )
        if self.recovery_run >= RECOVERY_ERROR_RUN:
            return ERROR, f"the last {self.recovery_run} updates all needed recovery"
        if rejected_now and steps == steps_then:
            return ERROR, f"every message rejected ({rejected_now} since the last report)"
        silent = self.silent()
        if len(silent) == len(INPUTS):
            age = min(a for _, a in silent)
            names = ", ".join(f"no {topics[w]}" for w, _ in silent)
            return STALE, f"inputs silent for {age:.1f} s ({names})"
        if grown:
            return WARN, "since the last report: " + ", ".join(grown)
        if silent:
            which, age = silent[0]
            return WARN, f"{topics[which]} silent for {age:.1f} s"
        if steps == 0:
            return OK, "waiting for paired images and actions"
        return OK, "tracking"

    def reported(self, counts: Mapping[str, int], steps: int) -> None:
        """Remember the counters of the report just published."""
        self._reported = (self.clock(), steps, dict(counts))
