"""Units of time: stamps are integer nanoseconds; one simulator step lasts 1 s (DESIGN.md)."""

from __future__ import annotations

__all__ = ["NS_PER_S", "STEP_NS"]

NS_PER_S = 1_000_000_000
"""Nanoseconds per second: stamps and ``builtin_interfaces/Time`` are split with it."""
STEP_NS = NS_PER_S
"""Duration of one step (DESIGN.md: 1 s of simulation time)."""
