"""Rewards on the step grid: a robot's reward stream summed per step, or a goal region.

The simulator stamps one reward per step (DESIGN.md); a real robot gives none unless told
to. ``learner policy`` takes a robot's rewards in one of two ways:

- a **reward stream** (:func:`step_reward_sums`): messages at their own times, each
  carrying a number. A step ``k`` earns the *sum* of the rewards timed in
  ``(t_k - period, t_k]``, and 0 when none falls there. Every reward then counts in
  exactly one step whatever the two rates, so the return (the sum over steps) is the sum
  of the rewards published: nothing is lost when two events fall in one step, nothing
  counted twice when a step has none. Event-like rewards (a bumper, "goal reached") need
  exactly this; a periodic stream is summed as well, so its per-step reward grows with its
  rate (a constant factor, which leaves the greedy policy unchanged);
- a **goal region** (:class:`GoalRegion`): ``reward`` for a step whose end pose (the pose
  at ``t_k``) lies within ``radius`` of a point, as the simulator's goal zone. The
  simulator's other rule, -1 for a step blocked by a wall, needs contact sensing that a
  pose cannot give, and has no counterpart here.

Numpy only; reading the messages is :mod:`tpsr_ros.io.reward_messages`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tpsr_ros.core.errors import ConfigError

__all__ = ["GOAL_REWARD", "GoalRegion", "step_reward_sums"]

GOAL_REWARD = 10.0
"""Reward of a step ending in the goal region (the simulator's goal reward)."""


@dataclass(frozen=True)
class GoalRegion:
    """A disc in the plane of the poses: a step ending inside earns ``reward``.

    Attributes:
        x, y: the centre (m, in the pose topic's frame).
        radius: m; a step ends inside when its end pose is closer than this (strictly, as
            the simulator's goal zone).
        reward: earned by such a step; 0 for every other step.

    """

    x: float
    y: float
    radius: float
    reward: float = GOAL_REWARD

    def __post_init__(self) -> None:
        for name in ("x", "y", "radius", "reward"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise ConfigError(f"the goal region's {name} must be a number, not {value!r}")
            if not math.isfinite(value):
                raise ConfigError(f"the goal region's {name} must be finite, not {value}")
            object.__setattr__(self, name, float(value))
        if self.radius <= 0:
            raise ConfigError(f"the goal region's radius must be positive, not {self.radius:g} m")

    @classmethod
    def parse(cls, text: str) -> GoalRegion:
        """``"X,Y,R"`` (metres) as a region; anything else raises ``ConfigError``."""
        parts = [p.strip() for p in str(text).split(",")]
        if len(parts) != 3:
            raise ConfigError(f"goal region {text!r} is not X,Y,R (three numbers, metres)")
        try:
            x, y, radius = (float(p) for p in parts)
        except ValueError:
            x = y = radius = math.nan  # refused below, as any non-finite number
        if not all(math.isfinite(v) for v in (x, y, radius)):
            raise ConfigError(f"goal region {text!r} is not X,Y,R (three finite numbers, metres)")
        return cls(x, y, radius)

    def rewards(self, positions: np.ndarray) -> np.ndarray:
        """``(T,)`` rewards of steps whose end poses are ``positions`` ``(T, >= 2)`` (x, y
        first); NaN where the pose is unknown (NaN)."""
        points = np.asarray(positions, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] < 2:
            raise ConfigError(f"positions must be (T, 2) or wider, not {points.shape}")
        distance = np.hypot(points[:, 0] - self.x, points[:, 1] - self.y)
        out = np.where(distance < self.radius, self.reward, 0.0)
        out[~np.isfinite(distance)] = np.nan
        return out

    def describe(self) -> str:
        """``"+10 within 15 m of (45, 45)"``: the rule in words."""
        return f"{self.reward:+g} within {self.radius:g} m of ({self.x:g}, {self.y:g})"


def step_reward_sums(
    times: np.ndarray, values: np.ndarray, step_stamps: np.ndarray, step_ns: int
) -> np.ndarray:
    """For each step time ``t``, the sum of the ``values`` timed in ``(t - step_ns, t]``.

    ``times`` (ns) need not be sorted; a step with no reward in its window earns 0 (see the
    module docstring for why a sum). Rewards outside every window (in a gap, before the
    first step) count nowhere. The step times must be increasing at least ``step_ns``
    apart (a grid's usable steps), so the windows do not overlap.
    """
    times = np.asarray(times, dtype=np.int64).reshape(-1)
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    at = np.asarray(step_stamps, dtype=np.int64).reshape(-1)
    if times.shape != values.shape:
        raise ConfigError(f"{times.size} reward times for {values.size} rewards")
    if step_ns <= 0:
        raise ConfigError(f"the step period must be positive, not {step_ns} ns")
    if not np.all(np.isfinite(values)):
        raise ConfigError("rewards must be finite")
    if np.any(np.diff(at) < step_ns):
        raise ConfigError("step times must increase by at least the step period")
    # each reward goes to the first step at or after it, if it lies in that step's window
    step = np.searchsorted(at, times, side="left")
    inside = step < at.size
    inside[inside] = at[step[inside]] - step_ns < times[inside]
    return np.bincount(step[inside], weights=values[inside], minlength=at.size).astype(np.float64)
