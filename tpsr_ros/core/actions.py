"""The simulator's discrete actions: grids of commands, one command component per axis.

Two grids, one per kind of robot:

- :data:`PLANAR` (the guide's robot, which never turns): x and y velocity each in
  {0, ±3, ±6} m per 1 s step; action ``5 * i + j`` commands ``(VELOCITIES[i],
  VELOCITIES[j])``, index 12 stands still. :data:`ACTIONS`, :data:`NUM_ACTIONS` and
  :func:`action_indices` are this grid's.
- :func:`drive_grid` (the ``drive`` environment, a differential-drive robot): forward speed
  in {0, 1.5, 3} m/s times turn rate in {-r, 0, +r} rad/s, as ``cmd_vel`` carries them
  (``linear.x``, ``angular.z``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from tpsr_ros.core.errors import ConfigError

__all__ = [
    "ACTIONS",
    "DEFAULT_TURN_RATE_DEG",
    "DRIVE_SPEEDS",
    "MAX_TURN_RATE_DEG",
    "NUM_ACTIONS",
    "PLANAR",
    "VELOCITIES",
    "ActionGrid",
    "action_index",
    "action_indices",
    "drive_grid",
    "environment_grid",
]


@dataclass(frozen=True, eq=False)
class ActionGrid:
    """Every combination of one level per command component, in row-major order.

    ``components`` name the ``Twist`` fields (``linear.x``, ``angular.z``...) and
    ``levels`` the values each takes, ascending.
    """

    components: tuple[str, ...]
    levels: tuple[tuple[float, ...], ...]

    def __post_init__(self) -> None:
        if len(self.components) != len(self.levels) or not self.components:
            raise ConfigError("an action grid needs one tuple of levels per component")
        for values in self.levels:
            if not values or list(values) != sorted(set(values)):
                raise ConfigError(f"grid levels {values} must be distinct and ascending")

    @cached_property
    def codes(self) -> np.ndarray:
        """``(K, len(components))``: the command of each action (read-only)."""
        mesh = np.meshgrid(*(np.asarray(v, dtype=np.float64) for v in self.levels), indexing="ij")
        codes = np.stack([m.ravel() for m in mesh], axis=1)
        codes.setflags(write=False)
        return codes

    def __len__(self) -> int:
        return math.prod(len(v) for v in self.levels)

    def indices(
        self, commands: np.ndarray, tolerance: float | tuple[float, ...] = np.inf
    ) -> np.ndarray:
        """Nearest action of each command row ``(N, len(components))``.

        Each component snaps independently to its nearest level. A component farther than
        ``tolerance`` (one for all, or one per component) from every level, or not finite,
        raises ``ConfigError``.
        """
        width = len(self.components)
        commands = np.asarray(commands, dtype=np.float64).reshape(-1, width)
        if not np.all(np.isfinite(commands)):
            raise ConfigError("velocity command is not finite")
        limits = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (width,))
        index = np.zeros(commands.shape[0], dtype=np.int64)
        excess = np.zeros(commands.shape[0], dtype=bool)
        for column, values in enumerate(self.levels):
            distance = np.abs(commands[:, column, None] - np.asarray(values)[None, :])
            index = index * len(values) + distance.argmin(axis=1)
            excess |= distance.min(axis=1) > limits[column]
        if excess.any():
            bad = commands[int(np.argmax(excess))]
            levels = "; ".join(
                f"{name} in {{{', '.join(f'{v:.4g}' for v in values)}}} ± {limit:.4g}"
                for name, values, limit in zip(self.components, self.levels, limits, strict=True)
            )
            raise ConfigError(
                f"command ({', '.join(f'{v:g}' for v in bad)}) is farther than the tolerance "
                f"from every action ({levels})"
            )
        return index

    def spacing(self) -> np.ndarray:
        """The smallest gap between two levels of each component (inf for a single level)."""
        return np.array([min(np.diff(v), default=np.inf) for v in self.levels])

    def command(self, action: int) -> dict[str, float]:
        """The command of ``action`` as component name to value."""
        return {
            name: float(value)
            for name, value in zip(self.components, self.codes[action], strict=True)
        }


VELOCITIES = np.array([-6.0, -3.0, 0.0, 3.0, 6.0])
PLANAR = ActionGrid(("linear.x", "linear.y"), (tuple(VELOCITIES), tuple(VELOCITIES)))
ACTIONS = PLANAR.codes
NUM_ACTIONS = len(PLANAR)

DRIVE_SPEEDS = (0.0, 1.5, 3.0)
"""Forward speeds of the ``drive`` robot, m/s."""
DEFAULT_TURN_RATE_DEG = 45.0
"""The ``drive`` robot's turn rate, degrees per 1 s step."""
MAX_TURN_RATE_DEG = 90.0
"""Largest turn rate accepted: beyond a quarter turn per step the camera's views of two
consecutive steps share little."""


@lru_cache(maxsize=8)
def drive_grid(turn_rate_deg: float = DEFAULT_TURN_RATE_DEG) -> ActionGrid:
    """The ``drive`` robot's 9 actions: :data:`DRIVE_SPEEDS` times turn {-r, 0, +r}."""
    if isinstance(turn_rate_deg, bool) or not (
        isinstance(turn_rate_deg, (int, float)) and 0 < turn_rate_deg <= MAX_TURN_RATE_DEG
    ):
        raise ConfigError(
            f"turn rate must be in (0, {MAX_TURN_RATE_DEG:g}] degrees per step, "
            f"got {turn_rate_deg!r}"
        )
    rate = math.radians(float(turn_rate_deg))
    return ActionGrid(("linear.x", "angular.z"), (DRIVE_SPEEDS, (-rate, 0.0, rate)))


def action_indices(velocities: np.ndarray, tolerance: float = np.inf) -> np.ndarray:
    """Nearest of the 25 planar actions for each ``(vx, vy)`` row of ``velocities``."""
    return PLANAR.indices(velocities, tolerance)


def action_index(vx: float, vy: float, tolerance: float = np.inf) -> int:
    """Nearest of the 25 planar actions to the velocity command ``(vx, vy)``."""
    return int(action_indices(np.array([[vx, vy]]), tolerance)[0])


def environment_grid(environment: str | None) -> ActionGrid:
    """The actions of a simulator environment by name: ``drive``'s 9 at the default turn
    rate, else (any other environment, or None: unknown) the 25 planar pairs."""
    return drive_grid() if environment == "drive" else PLANAR
