"""Exact-time pairing of two (or more) stamped streams, like message_filters' ExactTime.

The filter node needs, for every step k, the image o_k and the action a_k, which carry the
identical header stamp t_k (DESIGN.md). Messages arrive on separate topics, in any order
and interleaving; :class:`ExactTimeSynchronizer` buffers them by stamp and emits a step as
soon as every input has a message with that stamp. It is ROS-free (stamps are integer
nanoseconds, items are anything) and single-threaded.

Rules (each counted in :class:`PairingStats`):

- **pair**: the first time every input holds a message for stamp ``t``, the tuple is
  emitted and ``t`` becomes the *last emitted stamp* ``L``.
- **dropped** (incomplete steps): a buffered stamp is evicted without being emitted when
  (a) a newer stamp is emitted (its partner would now arrive too late: steps are used in
  stamp order, as message_filters' ExactTime clears tuples older than the last signal),
  (b) more than ``queue_size`` stamps are buffered (the oldest goes first), or (c)
  :meth:`ExactTimeSynchronizer.start_after` or :meth:`ExactTimeSynchronizer.clear`
  discards it. One count per evicted stamp.
- **duplicates**: a second message for a stamp already buffered on the same input, or for
  one of the last ``queue_size`` emitted stamps; the first message is kept.
- **late**: a message for a stamp at or before ``L`` (and not a duplicate) within the jump
  threshold: its step can no longer be used; it is discarded.
- **out_of_order**: a message whose stamp is earlier than the newest stamp received before
  on the same input (whatever then happens to it; most are still paired).
- **time_jumps**: a message earlier than ``L`` by more than ``jump_threshold_ns`` means
  time jumped backwards (a bag replayed with ``--loop``, a restarted simulator): everything
  buffered is dropped, ``L`` is forgotten, and the message starts afresh.
  :meth:`ExactTimeSynchronizer.check_time` applies the same test to other clocks
  (``/clock``, resets).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, fields
from enum import Enum
from typing import Any

from tpsr_ros.core.errors import ConfigError

__all__ = ["ExactTimeSynchronizer", "Outcome", "PairingStats", "Result"]


class Outcome(str, Enum):
    """What happened to one message given to :meth:`ExactTimeSynchronizer.add`."""

    BUFFERED = "buffered"
    PAIRED = "paired"
    DROPPED = "dropped"
    DUPLICATE = "duplicate"
    LATE = "late"


@dataclass
class PairingStats:
    """Counters of the synchroniser (see the module docstring for their rules)."""

    paired: int = 0
    dropped: int = 0
    duplicates: int = 0
    late: int = 0
    out_of_order: int = 0
    time_jumps: int = 0

    def as_dict(self) -> dict[str, int]:
        """Counter name to value."""
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}


@dataclass(frozen=True)
class Result:
    """Outcome of adding one message.

    Attributes:
        outcome: see :class:`Outcome`.
        stamp: the message's stamp (ns).
        items: the emitted tuple (one item per input) when ``outcome`` is PAIRED, else None.
        jumped: time jumped backwards before this message; the buffer was cleared first.

    """

    outcome: Outcome
    stamp: int
    items: tuple[Any, ...] | None = None
    jumped: bool = False


class ExactTimeSynchronizer:
    """Pairs ``n_inputs`` streams by identical stamp in a bounded buffer."""

    def __init__(
        self, n_inputs: int = 2, *, queue_size: int = 10, jump_threshold_ns: int = 5_000_000_000
    ) -> None:
        if n_inputs < 2:
            raise ConfigError(f"pairing needs at least 2 inputs, not {n_inputs}")
        if queue_size < 1:
            raise ConfigError(f"queue_size must be at least 1, not {queue_size}")
        if jump_threshold_ns < 0:
            raise ConfigError(f"the jump threshold must be >= 0, not {jump_threshold_ns} ns")
        self.n_inputs = n_inputs
        self.queue_size = queue_size
        self.jump_threshold_ns = int(jump_threshold_ns)
        self.stats = PairingStats()
        self._buffer: dict[int, list[Any]] = {}
        self._emitted: deque[int] = deque(maxlen=queue_size)
        self._newest: list[int | None] = [None] * n_inputs
        self.last_stamp: int | None = None
        """Stamp of the last emitted step (or the floor set by :meth:`start_after`)."""

    @property
    def pending(self) -> int:
        """Number of buffered, incomplete stamps."""
        return len(self._buffer)

    def _evict(self, stamps: list[int]) -> None:
        for stamp in stamps:
            del self._buffer[stamp]
        self.stats.dropped += len(stamps)

    def clear(self) -> None:
        """Forget everything buffered (counted as dropped) and the last emitted stamp."""
        self._evict(list(self._buffer))
        self._emitted.clear()
        self._newest = [None] * self.n_inputs
        self.last_stamp = None

    def is_jump(self, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` lies before the last emitted stamp by more than the threshold."""
        return self.last_stamp is not None and stamp_ns < self.last_stamp - self.jump_threshold_ns

    def check_time(self, stamp_ns: int) -> bool:
        """Apply the backwards-jump rule to another clock (``/clock``); True if time jumped."""
        if not self.is_jump(stamp_ns):
            return False
        self.stats.time_jumps += 1
        self.clear()
        return True

    def start_after(self, stamp_ns: int) -> None:
        """Start a new episode after ``stamp_ns``: drop buffered steps up to it, refuse older.

        Sets the last stamp to ``stamp_ns`` (never backwards: callers decide about resets
        older than the last step, see :meth:`is_jump`).
        """
        if self.last_stamp is not None and stamp_ns < self.last_stamp:
            raise ConfigError(f"start_after({stamp_ns}) is before the last stamp {self.last_stamp}")
        self._evict([s for s in self._buffer if s <= stamp_ns])
        self.last_stamp = stamp_ns

    def add(self, index: int, stamp_ns: int, item: Any) -> Result:
        """Add the message ``item`` (not None) of input ``index`` with stamp ``stamp_ns``."""
        if not 0 <= index < self.n_inputs:
            raise ConfigError(f"input index {index} is outside 0..{self.n_inputs - 1}")
        if item is None:
            raise ConfigError("a paired item cannot be None")
        stamp = int(stamp_ns)
        jumped = self.check_time(stamp)
        newest = self._newest[index]
        if newest is not None and stamp < newest:
            self.stats.out_of_order += 1
        else:
            self._newest[index] = stamp
        if self.last_stamp is not None and stamp <= self.last_stamp:
            if stamp in self._emitted:
                self.stats.duplicates += 1
                return Result(Outcome.DUPLICATE, stamp, jumped=jumped)
            self.stats.late += 1
            return Result(Outcome.LATE, stamp, jumped=jumped)
        slot = self._buffer.get(stamp)
        if slot is None:
            slot = self._buffer[stamp] = [None] * self.n_inputs
        elif slot[index] is not None:
            self.stats.duplicates += 1
            return Result(Outcome.DUPLICATE, stamp, jumped=jumped)
        slot[index] = item
        if all(x is not None for x in slot):
            del self._buffer[stamp]
            self._evict([s for s in self._buffer if s < stamp])
            self.last_stamp = stamp
            self._emitted.append(stamp)
            self.stats.paired += 1
            return Result(Outcome.PAIRED, stamp, tuple(slot), jumped)
        if len(self._buffer) > self.queue_size:
            self._evict(sorted(self._buffer)[: len(self._buffer) - self.queue_size])
            if stamp not in self._buffer:  # the new message itself was the oldest
                return Result(Outcome.DROPPED, stamp, jumped=jumped)
        return Result(Outcome.BUFFERED, stamp, jumped=jumped)
