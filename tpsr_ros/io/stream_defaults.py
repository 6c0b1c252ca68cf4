"""Defaults of robot-bag learning sized to the data, so that topics and a step period suffice.

- **observation size**: :data:`DEFAULT_LONGER_SIDE` pixels on the camera's longer side, its
  aspect kept (a smaller camera keeps its size); a size larger than the camera's is refused
  (area averaging cannot add detail, and the fit would only grow);
- **actions**: a k-means codebook of :func:`default_action_count` codes (one per
  :data:`STEPS_PER_ACTION` grid steps, 2 to 25), or of as many as the clusters the commands
  form when they form clear ones and are fewer (a robot driven by a few discrete commands:
  :func:`~tpsr_ros.core.codebook.cluster_count`), reduced until every code is the command
  in force at some grid step (:func:`supported_codebook`);
- **memory**: :func:`check_fit_memory` refuses, with the figures, a batch fit whose
  observations alone would not fit in this machine's memory.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from tpsr_ros.core.codebook import ActionCodebook, cluster_count, fit_codebook
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.resample import GridConfig, resample_grid
from tpsr_ros.io.bag_streams import BagStreams

__all__ = [
    "DEFAULT_LONGER_SIDE",
    "MAX_DEFAULT_ACTIONS",
    "STEPS_PER_ACTION",
    "check_fit_memory",
    "default_action_count",
    "default_image_size",
    "grid_step_count",
    "supported_codebook",
]

DEFAULT_LONGER_SIDE = 16
"""Observation pixels on the camera's longer side by default (the guide's 16x16 camera)."""
STEPS_PER_ACTION = 60
"""Grid steps per action of the default codebook: every per-action operator sees enough data."""
MAX_DEFAULT_ACTIONS = 25
"""The simulator's action count: the most the default codebook has."""
FIT_MEMORY_FACTOR = 4
"""Copies of the observation matrix a batch fit holds at its peak (observations, features,
their centred and whitened forms)."""


def default_image_size(camera: tuple[int, int]) -> tuple[int, int]:
    """(height, width) with :data:`DEFAULT_LONGER_SIDE` on the longer side, aspect kept."""
    height, width = camera
    longer = max(height, width)
    if longer <= DEFAULT_LONGER_SIDE:
        return height, width
    scale = DEFAULT_LONGER_SIDE / longer
    return max(1, round(height * scale)), max(1, round(width * scale))


def check_image_size(size: tuple[int, int], camera: tuple[int, int]) -> None:
    """Refuse an observation larger than the camera in either direction (upsampling)."""
    if size[0] > camera[0] or size[1] > camera[1]:
        raise ConfigError(
            f"--image-size {size[1]}x{size[0]} is larger than the camera's {camera[1]}x"
            f"{camera[0]}: resizing up adds no detail (give at most the camera's size)"
        )


def grid_step_count(streams: Sequence[BagStreams], grid: GridConfig) -> int:
    """Grid steps of the bags (usable or not), from their image spans."""
    return sum(
        max(0, int(s.image_times[-1] - s.image_times[0]) // grid.step_ns)
        for s in streams
        if s.image_times.size
    )


def default_action_count(steps: int) -> int:
    """One action per :data:`STEPS_PER_ACTION` steps, at least 2, at most 25."""
    return int(np.clip(steps // STEPS_PER_ACTION, 2, MAX_DEFAULT_ACTIONS))


def _commands_in_force(
    streams: Sequence[BagStreams], grid: GridConfig, columns: Sequence[int]
) -> np.ndarray:
    """The commands (of ``columns``) in force at the bags' usable grid steps."""
    parts = []
    for bag in streams:
        if bag.image_times.size == 0:
            continue
        steps = resample_grid(bag.image_times, bag.command_times, grid)
        parts.append(bag.commands[steps.command_index][:, list(columns)])
    return np.concatenate(parts) if parts else np.empty((0, len(columns)))


def supported_codebook(
    streams: Sequence[BagStreams],
    grid: GridConfig,
    components: tuple[str, ...],
    columns: Sequence[int],
    k: int,
    seed: int,
    *,
    reduce: bool,
) -> ActionCodebook:
    """A k-means codebook whose every code is the command in force at some grid step.

    Fitted on all commands. ``reduce`` (a default K): at most as many codes as the clusters
    the commands form, when they form clear ones, and fewer until each occurs; else a code
    that never occurs is refused, naming how many actions the data support.
    """
    commands = np.concatenate([s.commands[:, list(columns)] for s in streams])
    in_force = _commands_in_force(streams, grid, columns)
    if in_force.shape[0] == 0:
        raise DataError("no grid step has a command in force: check --step-period and topics")
    if reduce:
        k = min(k, np.unique(commands, axis=0).shape[0])
        k = min(k, cluster_count(commands, k, seed) or k)

    def covering(count: int) -> ActionCodebook | None:
        codebook = fit_codebook(commands, components, count, seed)
        occurring = np.unique(codebook.assign(in_force)[0]).size
        return codebook if occurring == count else None

    if (codebook := covering(k)) is not None:
        return codebook
    # the largest count whose codes all occur, by bisection (a few k-means fits, not k);
    # one code always occurs, as some step has a command in force
    low, high, best = 1, k - 1, covering(1)
    while low < high:
        middle = (low + high + 1) // 2
        if (found := covering(middle)) is not None:
            low, best = middle, found
        else:
            high = middle - 1
    if reduce and best is not None:
        return best
    raise DataError(
        f"{k} actions: some code is never the command in force at a step; the data support "
        f"{low} (give --actions {low} or record more varied commands)"
    )


def physical_memory() -> int | None:
    """This machine's memory in bytes, or None where the OS does not say."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def check_fit_memory(steps: int, values_per_step: int, memory: int | None = None) -> int:
    """Refuse a batch fit of ``steps`` observations of ``values_per_step`` values that would
    need more than this machine's memory; return the estimate in bytes."""
    need = FIT_MEMORY_FACTOR * 8 * int(steps) * int(values_per_step)
    memory = physical_memory() if memory is None else memory
    if memory is not None and need > memory:
        raise ConfigError(
            f"{steps} steps of {values_per_step} observation values need about "
            f"{need / 2**30:.1f} GiB to fit, more than this machine's {memory / 2**30:.1f} GiB: "
            "give a smaller --image-size, or --stream"
        )
    return need
