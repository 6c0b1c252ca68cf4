"""The 25 velocity actions: x and y velocity each in {0, ±3, ±6} m per 1 s step.

Action ``5 * i + j`` commands ``(VELOCITIES[i], VELOCITIES[j])``; index 12 stands still.
"""

from __future__ import annotations

import numpy as np

from tpsr_ros.core.errors import ConfigError

__all__ = ["ACTIONS", "NUM_ACTIONS", "VELOCITIES", "action_index", "action_indices"]

VELOCITIES = np.array([-6.0, -3.0, 0.0, 3.0, 6.0])
ACTIONS = np.array([(vx, vy) for vx in VELOCITIES for vy in VELOCITIES])
NUM_ACTIONS = len(ACTIONS)


def action_indices(velocities: np.ndarray, tolerance: float = np.inf) -> np.ndarray:
    """Nearest action index for each ``(vx, vy)`` row of ``velocities`` (shape ``(N, 2)``).

    Each component snaps independently to the nearest of {0, ±3, ±6}. A component farther
    than ``tolerance`` from every velocity, or not finite, raises ``ConfigError``.
    """
    velocities = np.asarray(velocities, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(velocities)):
        raise ConfigError("velocity command is not finite")
    distance = np.abs(velocities[:, :, None] - VELOCITIES[None, None, :])
    nearest = distance.argmin(axis=2)
    if np.any(distance.min(axis=2) > tolerance):
        worst = velocities[np.argmax(distance.min(axis=2).max(axis=1))]
        raise ConfigError(
            f"velocity ({worst[0]:g}, {worst[1]:g}) is farther than {tolerance:g} m/s "
            f"from every action in {{0, ±3, ±6}}"
        )
    return nearest[:, 0] * len(VELOCITIES) + nearest[:, 1]


def action_index(vx: float, vy: float, tolerance: float = np.inf) -> int:
    """Nearest of the 25 actions to the velocity command ``(vx, vy)``."""
    return int(action_indices(np.array([[vx, vy]]), tolerance)[0])
