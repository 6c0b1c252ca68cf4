"""Streams at their own rates onto a fixed step grid (``learner fit --step-period``).

A robot records its camera and its velocity commands at their own rates and clocks. The
learner and the filter node need steps ``(a_k, o_k)`` one period apart. The rules, shared by
offline reading (:func:`resample_grid`, vectorised) and the filter node
(:class:`GridStepper`, one message at a time):

- **grid**: step times ``t_k = phase + k * period`` (absolute times: the grid does not
  depend on which message came first). The phase is chosen from the training data to keep
  step times far from image and command events (:func:`choose_phase`), so stamp jitter and
  the timing of unstamped commands never decide which side of a step an event falls on.
  Models written before phases existed keep their rule: ``t_k = origin + k * period`` from
  half a camera period after the first image. A stream's steps are those after its first
  image and before its last;
- **observation**: the latest image at or before ``t_k``; if it is older than
  ``image_timeout`` (camera silence), the step is a gap;
- **action**: the command in force at ``t_k``: the latest command at or before ``t_k``,
  held for at most ``command_timeout``; no command in force makes the step a gap. A
  command's time is its header stamp; an unstamped one (``Twist``, or a zero stamp) is
  dated by the stamp of the first image after it, in the bag's order offline and in the
  publishers' send order online: only the order of messages decides, which a replay keeps;
- **online** (:class:`GridStepper`): step ``k`` closes once both streams have passed
  ``t_k`` (an image and a command later than ``t_k`` arrived), or once either stream is
  ``max_latency`` past ``t_k`` (the other is late or silent), or on :meth:`GridStepper.flush`
  (both silent). Messages of each stream in order, interleaved in any order within the
  latency bound, give exactly the offline steps.

A gap ends the segment (the next step restarts from ``b_*``). Images must arrive in stamp
order; an image not newer than the one before is dropped (:func:`increasing`).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Any

import numpy as np

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.units import NS_PER_S

__all__ = [
    "GridConfig",
    "GridStep",
    "GridStepper",
    "ResampledSteps",
    "choose_phase",
    "grid_times",
    "increasing",
    "resample_grid",
]

PHASE_CANDIDATES = 200
"""Phases :func:`choose_phase` compares, evenly over one period."""
MAX_PHASE_EVENTS = 20_000
"""Events :func:`choose_phase` scores at most (an even subsample of more)."""


@dataclass(frozen=True)
class GridConfig:
    """The step grid of a model learned with ``--step-period``.

    Attributes:
        step_ns: the step period.
        camera_period_ns: the camera's median frame interval in the training data.
        image_timeout_ns: oldest usable image at a step (longer camera silence: a gap).
        command_timeout_ns: how long a command stays in force.
        phase_ns: step times are the times congruent to it modulo ``step_ns``
            (``0 <= phase_ns < step_ns``); None: the origin rule of older models.

    """

    step_ns: int
    camera_period_ns: int
    image_timeout_ns: int
    command_timeout_ns: int
    phase_ns: int | None = None

    def __post_init__(self) -> None:
        for name in ("step_ns", "camera_period_ns", "image_timeout_ns", "command_timeout_ns"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ConfigError(f"{name} must be a positive integer (ns), not {value!r}")
            object.__setattr__(self, name, int(value))
        phase = self.phase_ns
        if phase is not None:
            if (
                isinstance(phase, bool)
                or not isinstance(phase, (int, np.integer))
                or not (0 <= phase < self.step_ns)
            ):
                raise ConfigError(f"phase_ns must be in [0, step_ns), not {phase!r}")
            object.__setattr__(self, "phase_ns", int(phase))

    def as_dict(self) -> dict[str, Any]:
        """JSON form (seconds) stored in model metadata."""
        values = {
            "step_period_s": self.step_ns / NS_PER_S,
            "camera_period_s": self.camera_period_ns / NS_PER_S,
            "image_timeout_s": self.image_timeout_ns / NS_PER_S,
            "command_timeout_s": self.command_timeout_ns / NS_PER_S,
        }
        if self.phase_ns is not None:
            values["phase_s"] = self.phase_ns / NS_PER_S
        return values

    @classmethod
    def from_dict(cls, data: Any) -> GridConfig:
        """Inverse of :meth:`as_dict`; malformed values raise ``ConfigError``."""
        if not isinstance(data, dict):
            raise ConfigError("the step grid is not an object")
        values = []
        for key in ("step_period_s", "camera_period_s", "image_timeout_s", "command_timeout_s"):
            value = data.get(key)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"the step grid lacks a number {key!r}")
            if not (np.isfinite(value) and 0 < value < 1e6):
                raise ConfigError(f"the step grid's {key} {value!r} is not in (0, 1e6) s")
            values.append(round(value * NS_PER_S))
        phase = data.get("phase_s")
        if phase is not None:
            if (
                isinstance(phase, bool)
                or not isinstance(phase, (int, float))
                or not (np.isfinite(phase) and 0 <= phase < data["step_period_s"])
            ):
                raise ConfigError(f"the step grid's phase_s {phase!r} is not in [0, the period)")
            phase = min(round(phase * NS_PER_S), values[0] - 1)
        step, camera, image, command = values
        return cls(step, camera, image, command, phase_ns=phase)


def first_step(first_image_ns: int, config: GridConfig) -> int:
    """Time of a stream's first step: the first grid time after its first image."""
    first = int(first_image_ns)
    if config.phase_ns is None:
        return first + config.camera_period_ns // 2
    step = config.step_ns
    return first + 1 + (config.phase_ns - first - 1) % step


def grid_times(first_image_ns: int, last_image_ns: int, config: GridConfig) -> np.ndarray:
    """Every step time of a stream whose images span ``[first, last]``: after the first
    image, before the last."""
    start = first_step(first_image_ns, config)
    count = max(0, -(-(int(last_image_ns) - start) // config.step_ns))  # t_k < last image
    return start + np.arange(count, dtype=np.int64) * config.step_ns


def choose_phase(
    events_ns: np.ndarray, step_ns: int, spans_ns: np.ndarray | None = None
) -> int:
    """The phase whose step times lie farthest from the events (image and command times).

    An event may be a span (``spans_ns``: its length, e.g. from when an unstamped command
    was logged to the image that dates it): a step inside it is at distance 0. Each of
    :data:`PHASE_CANDIDATES` phases is scored by the 5th percentile of the distance from the
    events to the nearest step time (all events fold into one period); the best wins, the
    earliest among equals. A step time far from every event makes which side of it an event
    falls on immune to stamp jitter and to how a command was timed.
    """
    events = np.asarray(events_ns, dtype=np.int64)
    if events.size == 0:
        return 0
    spans = np.zeros(events.size) if spans_ns is None else np.asarray(spans_ns, np.float64)
    if events.size > MAX_PHASE_EVENTS:  # an even subsample keeps the cost bounded
        pick = np.linspace(0, events.size - 1, MAX_PHASE_EVENTS).astype(np.int64)
        events, spans = events[pick], spans[pick]
    start = (events % step_ns).astype(np.float64)
    candidates = np.arange(PHASE_CANDIDATES, dtype=np.float64) * step_ns / PHASE_CANDIDATES
    after_start = (candidates[:, None] - start[None, :]) % step_ns  # candidate past the start
    inside = after_start <= spans[None, :]
    before = step_ns - after_start  # to the span's start, going forward
    beyond = after_start - np.minimum(spans, step_ns)[None, :]  # past the span's end
    distance = np.where(inside, 0.0, np.minimum(before, beyond))
    score = np.percentile(distance, 5, axis=1)
    return round(float(candidates[int(np.argmax(score))]))


def increasing(times: np.ndarray) -> np.ndarray:
    """Mask of the entries newer than every entry before them (arrival order kept)."""
    times = np.asarray(times, dtype=np.int64)
    if times.size == 0:
        return np.zeros(0, dtype=bool)
    before = np.maximum.accumulate(np.concatenate([[np.iinfo(np.int64).min], times[:-1]]))
    return times > before


@dataclass(frozen=True)
class ResampledSteps:
    """The grid steps of one stream pair.

    Attributes:
        stamps: ``(S,)`` step times ``t_k`` of the usable steps (int64 ns).
        image_index: ``(S,)`` index of each step's image in the image times given.
        command_index: ``(S,)`` index of each step's command in the command times given.
        grid_steps: number of grid points between the first and last image.
        fresh: grid points with at least one new image since the previous grid point.
        stale_image, no_command: grid points that were gaps for each reason.

    """

    stamps: np.ndarray
    image_index: np.ndarray
    command_index: np.ndarray
    grid_steps: int
    fresh: int
    stale_image: int
    no_command: int


def resample_grid(
    image_times: np.ndarray, command_times: np.ndarray, config: GridConfig
) -> ResampledSteps:
    """Grid steps of increasing ``image_times`` and sorted ``command_times`` (module rules)."""
    images = np.asarray(image_times, dtype=np.int64)
    commands = np.asarray(command_times, dtype=np.int64)
    if images.size == 0 or np.any(np.diff(images) <= 0):
        raise ConfigError("image times must be non-empty and increasing")
    if np.any(np.diff(commands) < 0):
        raise ConfigError("command times must be sorted")
    grid = grid_times(int(images[0]), int(images[-1]), config)
    count = int(grid.size)
    image_index = np.searchsorted(images, grid, side="right") - 1
    newest_before = np.searchsorted(images, grid - config.step_ns, side="right") - 1
    fresh = int(np.count_nonzero(image_index > newest_before))
    image_ok = grid - images[image_index] <= config.image_timeout_ns
    command_index = np.searchsorted(commands, grid, side="right") - 1
    has_command = command_index >= 0
    command_age = grid - commands[np.maximum(command_index, 0)] if commands.size else grid
    command_ok = has_command & (command_age <= config.command_timeout_ns)
    usable = image_ok & command_ok
    return ResampledSteps(
        stamps=grid[usable],
        image_index=image_index[usable],
        command_index=command_index[usable],
        grid_steps=int(count),
        fresh=fresh,
        stale_image=int(np.count_nonzero(~image_ok)),
        no_command=int(np.count_nonzero(image_ok & ~command_ok)),
    )


def _time_of(entry: tuple[int, Any]) -> int:
    return entry[0]


@dataclass(frozen=True)
class GridStep:
    """One step of :class:`GridStepper`: its time, image (as given) and command (as given)."""

    stamp: int
    image: Any
    command: Any


class GridStepper:
    """The rules of :func:`resample_grid`, applied to messages as they arrive.

    Feed images with :meth:`add_image` and commands with :meth:`add_command` (each stream
    in its own order, the two interleaved in any order); each returns the steps it closes
    (module docstring: both streams past ``t_k``, or one ``max_latency_ns`` past it).
    :meth:`flush` closes the steps before the newest image when both streams fell silent.
    Counters: ``images``, ``commands``, ``images_out_of_order`` (not newer than the previous
    image: dropped), ``late`` (messages at or before a closed step: they changed nothing),
    ``camera_gaps`` and ``command_gaps`` (grid steps that were gaps), ``steps``.
    """

    def __init__(
        self, config: GridConfig, max_latency_ns: int = NS_PER_S, command_history: int = 256
    ) -> None:
        if max_latency_ns < 0:
            raise ConfigError(f"the latency bound must be >= 0 ns, not {max_latency_ns}")
        self.config = config
        self.max_latency_ns = int(max_latency_ns)
        self._command_history = command_history
        self.images = self.commands = self.images_out_of_order = self.late = 0
        self.camera_gaps = self.command_gaps = self.steps = 0
        self.reset()

    def reset(self) -> None:
        """Forget every image, command and step: a new grid starts at the next image."""
        self._images: list[tuple[int, Any]] = []  # (time, image), increasing
        self._commands: list[tuple[int, Any]] = []  # (time, command), in time order
        self._next: int | None = None  # time of the next step to close
        self._closed: int | None = None  # time of the last step closed
        self.origin: int | None = None
        self.command_time: int | None = None  # newest command time

    @property
    def last_image_time(self) -> int | None:
        """Time of the newest image (ns), or None."""
        return self._images[-1][0] if self._images else None

    @property
    def last_image(self) -> tuple[int, Any] | None:
        """The newest image ``(time, image)``, or None."""
        return self._images[-1] if self._images else None

    def add_command(self, time_ns: int, command: Any) -> list[GridStep]:
        """A command in force from ``time_ns`` on (kept in time order); the steps it closes."""
        self.commands += 1
        time_ns = int(time_ns)
        if self._closed is not None and time_ns <= self._closed:
            self.late += 1
        index = bisect.bisect_right(self._commands, time_ns, key=_time_of)
        self._commands.insert(index, (time_ns, command))
        if len(self._commands) > self._command_history:
            del self._commands[0]  # the oldest: keep the latest command_history
        if self.command_time is None or time_ns > self.command_time:
            self.command_time = time_ns
        return self._close()

    def add_image(self, time_ns: int, image: Any) -> list[GridStep]:
        """Add an image; return the steps it closes."""
        time_ns = int(time_ns)
        if self._images and time_ns <= self._images[-1][0]:
            self.images_out_of_order += 1
            return []
        self.images += 1
        if self._closed is not None and time_ns <= self._closed:
            self.late += 1
        self._images.append((time_ns, image))
        if self._next is None:
            self._next = self.origin = first_step(time_ns, self.config)
        return self._close()

    def flush(self) -> list[GridStep]:
        """Close every step before the newest image (both streams silent: nothing else comes)."""
        return self._close(everything=True)

    def _command_at(self, time_ns: int) -> Any | None:
        index = bisect.bisect_right(self._commands, time_ns, key=_time_of) - 1
        if index < 0 or time_ns - self._commands[index][0] > self.config.command_timeout_ns:
            return None
        return self._commands[index][1]

    def _image_at(self, time_ns: int) -> tuple[int, Any] | None:
        index = bisect.bisect_right(self._images, time_ns, key=_time_of) - 1
        return self._images[index] if index >= 0 else None

    def _due(self, t: int, everything: bool) -> bool:
        """Whether step time ``t`` can close: it precedes the newest image, and both streams
        passed it, or one passed it by the latency bound (or ``everything``)."""
        newest_image = self._images[-1][0]
        if t >= newest_image:
            return False
        if everything:
            return True
        commands = self.command_time
        if commands is not None and commands > t:
            return True
        return max(newest_image, commands or newest_image) - t >= self.max_latency_ns

    def _close(self, everything: bool = False) -> list[GridStep]:
        steps: list[GridStep] = []
        while self._next is not None and self._images and self._due(self._next, everything):
            t = self._next
            image = self._image_at(t)
            assert image is not None  # the first step lies after the first image
            if t - image[0] > self.config.image_timeout_ns:
                # camera silence: every step up to the next image is a gap
                following = self._images[bisect.bisect_right(self._images, t, key=_time_of)][0]
                skipped = -(-(following - t) // self.config.step_ns)
                self.camera_gaps += skipped
                self._closed = t + (skipped - 1) * self.config.step_ns
                self._next = self._closed + self.config.step_ns
                continue
            if (command := self._command_at(t)) is None:
                self.command_gaps += 1
            else:
                steps.append(GridStep(t, image[1], command))
                self.steps += 1
            self._closed = t
            self._next = t + self.config.step_ns
        self._forget()
        return steps

    def _forget(self) -> None:
        """Drop images no step can take any more (all but the latest at or before the next)."""
        if self._next is None:
            return
        keep = bisect.bisect_right(self._images, self._next, key=_time_of) - 1
        if keep > 0:
            del self._images[:keep]
