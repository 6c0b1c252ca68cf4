"""Distractor motion: reflected Gaussian random walks, one step per simulator step.

A reflected walk equals the free walk folded into the allowed interval, so a whole
trajectory is a cumulative sum and a fold (``distractor_paths``) and the step-by-step
``Distractors`` draws the same numbers in the same order: with the same generator both
give identical positions.
"""

from __future__ import annotations

import numpy as np

from sim_node.config import SimConfig

__all__ = ["Distractors", "distractor_paths"]


def _fold(x: np.ndarray, low: float, high: float) -> np.ndarray:
    """Mirror ``x`` into ``[low, high]`` (the position of a walk reflected at both ends)."""
    width = high - low
    phase = np.mod(x - low, 2.0 * width)
    return low + width - np.abs(phase - width)


def _bounds(config: SimConfig) -> tuple[tuple[float, float], tuple[float, float]]:
    cfg, size = config.distractors, config.room_size
    floor = (cfg.floor_radius, size - cfg.floor_radius)
    wall = (cfg.wall_half_width, size - cfg.wall_half_width)
    return floor, wall


def _initial(config: SimConfig, rng: np.random.Generator) -> np.ndarray:
    """Free-walk start: ``F * 2`` floor coordinates then 4 wall coordinates."""
    (f_lo, f_hi), (w_lo, w_hi) = _bounds(config)
    count = config.distractors.floor_count
    floor = rng.uniform(f_lo, f_hi, size=2 * count)
    walls = rng.uniform(w_lo, w_hi, size=4)
    return np.concatenate([floor, walls])


def _split(config: SimConfig, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fold free coordinates ``(..., 2F + 4)`` into floor ``(..., F, 2)`` and walls ``(..., 4)``."""
    (f_lo, f_hi), (w_lo, w_hi) = _bounds(config)
    count = config.distractors.floor_count
    floor = _fold(free[..., : 2 * count], f_lo, f_hi).reshape(*free.shape[:-1], count, 2)
    walls = _fold(free[..., 2 * count :], w_lo, w_hi)
    return floor, walls


class Distractors:
    """Current distractor positions, advanced one step at a time."""

    def __init__(self, config: SimConfig, rng: np.random.Generator) -> None:
        self._config = config
        self._rng = rng
        self._free = _initial(config, rng)

    def advance(self) -> None:
        """Move every distractor by one random-walk step."""
        std = self._config.distractors.step_std
        self._free = self._free + std * self._rng.standard_normal(self._free.size)

    def positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Floor disk centres ``(F, 2)`` and wall rectangle centres ``(4,)``."""
        return _split(self._config, self._free)


def distractor_paths(
    config: SimConfig, rng: np.random.Generator, steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Initial positions and ``steps`` advanced positions, drawn as ``Distractors`` does.

    Returns floor ``(F, 2)``, walls ``(4,)`` at reset, then floor ``(steps, F, 2)`` and
    walls ``(steps, 4)`` after each step.
    """
    start = _initial(config, rng)
    std = config.distractors.step_std
    increments = std * rng.standard_normal((steps, start.size))
    # accumulate from the start so additions happen in the same order as Distractors.advance
    free = np.cumsum(np.vstack([start, increments]), axis=0)[1:]
    floor0, walls0 = _split(config, start)
    floor, walls = _split(config, free)
    return floor0, walls0, floor, walls
