"""Streams at their own rates onto a fixed step grid (``learner fit --step-period``).

A robot records its camera and its velocity commands at their own rates and clocks. The
learner and the filter node need steps ``(a_k, o_k)`` one period apart. The rules, shared by
offline reading (:func:`resample_grid`, vectorised) and the filter node
(:class:`GridStepper`, one message at a time, in arrival order):

- **grid**: step times ``t_k = origin + k * period`` with ``origin`` = the first image time
  plus half the camera period (so image stamp jitter below half a camera period never
  changes which image a step takes); a step exists once an image *later* than ``t_k`` has
  arrived, so the last step lies before the last image;
- **observation**: the latest image at or before ``t_k``; if it is older than
  ``image_timeout`` (camera silence), the step is a gap;
- **action**: the command in force at ``t_k``: the latest command at or before ``t_k``,
  held for at most ``command_timeout``; no command in force makes the step a gap.

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
    "grid_origin",
    "increasing",
    "resample_grid",
]


@dataclass(frozen=True)
class GridConfig:
    """The step grid of a model learned with ``--step-period``.

    Attributes:
        step_ns: the step period.
        camera_period_ns: the camera's median frame interval in the training data; the grid
            starts half of it after the first image.
        image_timeout_ns: oldest usable image at a step (longer camera silence: a gap).
        command_timeout_ns: how long a command stays in force.

    """

    step_ns: int
    camera_period_ns: int
    image_timeout_ns: int
    command_timeout_ns: int

    def __post_init__(self) -> None:
        for name in ("step_ns", "camera_period_ns", "image_timeout_ns", "command_timeout_ns"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ConfigError(f"{name} must be a positive integer (ns), not {value!r}")
            object.__setattr__(self, name, int(value))

    def as_dict(self) -> dict[str, Any]:
        """JSON form (seconds) stored in model metadata."""
        return {
            "step_period_s": self.step_ns / NS_PER_S,
            "camera_period_s": self.camera_period_ns / NS_PER_S,
            "image_timeout_s": self.image_timeout_ns / NS_PER_S,
            "command_timeout_s": self.command_timeout_ns / NS_PER_S,
        }

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
        return cls(*values)


def grid_origin(first_image_ns: int, config: GridConfig) -> int:
    """Time of step 0: half a camera period after the first image."""
    return int(first_image_ns) + config.camera_period_ns // 2


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
    origin = grid_origin(int(images[0]), config)
    count = max(0, -(-(int(images[-1]) - origin) // config.step_ns))  # t_k < last image
    grid = origin + np.arange(count, dtype=np.int64) * config.step_ns
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

    Feed commands with :meth:`add_command` and images with :meth:`add_image`; each image
    completes the grid steps before it and returns them. Given the messages of a bag in
    its order, the steps equal :func:`resample_grid`'s (the commands of a step must have
    arrived before the image that completes it). Counters: ``images``, ``commands``,
    ``images_out_of_order`` (not newer than the previous image: dropped),
    ``camera_gaps`` and ``command_gaps`` (grid steps that were gaps), ``steps``.
    """

    def __init__(self, config: GridConfig, command_history: int = 256) -> None:
        self.config = config
        self._command_history = command_history
        self._commands: list[tuple[int, Any]] = []  # (time, command), in time order
        self.images = self.commands = self.images_out_of_order = 0
        self.camera_gaps = self.command_gaps = self.steps = 0
        self.reset()

    def reset(self) -> None:
        """Forget grid, last image and commands: a new grid starts at the next image."""
        self.origin: int | None = None
        self._next = 0
        self.last_image: tuple[int, Any] | None = None
        self._commands.clear()

    @property
    def last_image_time(self) -> int | None:
        """Time of the newest image (ns), or None."""
        return None if self.last_image is None else self.last_image[0]

    def add_command(self, time_ns: int, command: Any) -> None:
        """A command in force from ``time_ns`` on (kept in time order)."""
        self.commands += 1
        time_ns = int(time_ns)
        index = bisect.bisect_right(self._commands, time_ns, key=_time_of)
        self._commands.insert(index, (time_ns, command))
        if len(self._commands) > self._command_history:
            del self._commands[0]  # the oldest: keep the latest command_history

    def _command_at(self, time_ns: int) -> Any | None:
        index = bisect.bisect_right(self._commands, time_ns, key=_time_of) - 1
        if index < 0 or time_ns - self._commands[index][0] > self.config.command_timeout_ns:
            return None
        return self._commands[index][1]

    def add_image(self, time_ns: int, image: Any) -> list[GridStep]:
        """Add an image; return the grid steps it completes (those before ``time_ns``)."""
        time_ns = int(time_ns)
        if self.last_image is not None and time_ns <= self.last_image[0]:
            self.images_out_of_order += 1
            return []
        self.images += 1
        steps: list[GridStep] = []
        if self.origin is None:
            self.origin = grid_origin(time_ns, self.config)
            self._next = 0
        elif self.last_image is not None:
            step = self.config.step_ns
            last_time, last = self.last_image
            due = -(-(time_ns - self.origin) // step)  # grid points before time_ns
            while self._next < due:
                t = self.origin + self._next * step
                if t - last_time > self.config.image_timeout_ns:
                    self.camera_gaps += due - self._next  # camera silence up to this image
                    self._next = due
                    break
                command = self._command_at(t)
                if command is None:
                    self.command_gaps += 1
                else:
                    steps.append(GridStep(t, last, command))
                    self.steps += 1
                self._next += 1
        self.last_image = (time_ns, image)
        return steps
