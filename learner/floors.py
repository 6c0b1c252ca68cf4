"""The floors of every results table: the best state-blind policies (DESIGN.md).

A learned representation is worth something only where its policy beats every policy
that ignores the state. Two floors run the standard protocol (:mod:`learner.evaluate`)
without looking at what the robot sees:

- ``constant``: the best of the constant actions (25, or ``drive``'s 9: the best
  state-blind policy that does not randomise). It is deterministic: the protocol's seed
  fixes the execution noise, so every repetition of an experiment scores the same and its SEM is 0.
- ``random``: uniformly random actions from a seeded generator (one seed per run).

Neither uses training data, so the results page pools each floor over all its runs of an
experiment, whatever their data size (:func:`learner.tables.pooled_floors`); an
experiment's random run draws its policy seed from the grid's seed, the demo runs it once
with :data:`DEMO_POLICY_SEED`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from learner.evaluate import EVALUATION_SEED, Evaluation, run_protocol
from sim_node import SimConfig
from tpsr_ros.core.episodes import Trajectory

__all__ = [
    "CONSTANT",
    "DEMO_POLICY_SEED",
    "FLOORS",
    "RANDOM",
    "BlindTracker",
    "ConstantFloor",
    "constant_floor",
    "random_floor",
]

CONSTANT = "constant"
RANDOM = "random"
FLOORS = (CONSTANT, RANDOM)
DEMO_POLICY_SEED = 0
"""The random floor's policy seed in ``make demo`` (``python -m learner.demo``): one run."""
_NO_STATE = np.zeros(0)


@dataclass(frozen=True)
class BlindTracker:
    """A tracker whose state is empty: the controller sees nothing of the robot."""

    representation: str = "none"
    fingerprint: str = "none"
    sees_images: bool = False

    def start(self, image: np.ndarray, position: np.ndarray) -> np.ndarray:
        """The empty state."""
        return _NO_STATE

    def step(
        self, state: np.ndarray, action: int, image: np.ndarray, position: np.ndarray
    ) -> np.ndarray:
        """The empty state, whatever happened."""
        return _NO_STATE

    def track(self, trajectory: Trajectory) -> np.ndarray:
        """An empty state per step."""
        return np.zeros((len(trajectory), 0))


@dataclass(frozen=True)
class ConstantFloor:
    """The best constant action and its evaluation."""

    action: int
    evaluation: Evaluation
    velocity: tuple[float, float]
    """The action's command: ``(vx, vy)`` in m/s, or ``drive``'s (speed, turn rate)."""


@lru_cache(maxsize=4)
def constant_floor(environment: str, seed: int = EVALUATION_SEED) -> ConstantFloor:
    """Evaluate every constant action; the best (lowest index on a tie) is the floor."""
    grid = SimConfig(environment=environment).actions
    results = [
        run_protocol(lambda _state, a=action: a, BlindTracker(), environment, seed=seed)
        for action in range(len(grid))
    ]
    best = int(np.argmax([r.score for r in results]))
    first, second = grid.codes[best]
    return ConstantFloor(best, results[best], (float(first), float(second)))


def random_floor(environment: str, policy_seed: int, seed: int = EVALUATION_SEED) -> Evaluation:
    """Uniformly random actions drawn from ``policy_seed`` under the standard protocol."""
    rng = np.random.default_rng(policy_seed)
    count = len(SimConfig(environment=environment).actions)

    def choose(_state: np.ndarray) -> int:
        return int(rng.integers(count))

    return run_protocol(choose, BlindTracker(), environment, seed=seed)
