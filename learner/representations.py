"""State trackers for planning and evaluation: a learned model, or the true position.

The learning core's :class:`~tpsr_ros.core.state_model.StateModel` turns images and actions
into states. The true-position baseline (the upper bound of the RL step) reads the
simulator's ground truth instead, which is allowed only here, in evaluation and
planning, never in learning. Both sit behind one small interface so the fitted-Q and
evaluation code treat them alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from tpsr_ros.core.episodes import Trajectory, image_to_observation, track_trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.images import Preprocessing, preprocess_images
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.io.model_io import ModelFile, open_model
from tpsr_ros.io.policy import TRUE_POSITION

__all__ = ["ModelTracker", "Tracker", "TruePositionTracker", "load_tracker"]


class Tracker(Protocol):
    """Turns what the robot sees (and the ground truth, for the baseline) into states."""

    representation: str
    fingerprint: str

    def start(self, image: np.ndarray, position: np.ndarray) -> np.ndarray:
        """State at the start of a run, before any action."""

    def step(
        self, state: np.ndarray, action: int, image: np.ndarray, position: np.ndarray
    ) -> np.ndarray:
        """State after ``action`` was executed and ``image`` seen."""

    def track(self, trajectory: Trajectory) -> np.ndarray:
        """States ``(T, d)`` after each step of a recorded trajectory (restarting at gaps)."""


@dataclass(frozen=True)
class ModelTracker:
    """A learned model (TPSR or PCA): starts at its initial state, never sees ground truth.

    ``preprocessing``: a robot model's own (its camera's images resized as the filter node
    resizes them); None: the simulator's images as they are (pixels / 255).
    """

    model: StateModel
    fingerprint: str
    preprocessing: Preprocessing | None = None

    @property
    def representation(self) -> str:
        """``"tpsr"`` or ``"pca"``."""
        return str(self.model.method)

    def start(self, image: np.ndarray, position: np.ndarray) -> np.ndarray:
        """``b_*`` for a TPSR: no observation has been paired with an action yet."""
        return self.model.initial_state()

    def step(
        self, state: np.ndarray, action: int, image: np.ndarray, position: np.ndarray
    ) -> np.ndarray:
        """One update with the model's parameters (Algorithm 4 for a TPSR)."""
        if self.preprocessing is None:
            observation = image_to_observation(image)
        else:
            observation = preprocess_images(image[None], self.preprocessing)[0]
        return self.model.update(state, action, observation)[0]

    def track(self, trajectory: Trajectory) -> np.ndarray:
        """States tracked with the model's parameters over the trajectory."""
        return track_trajectory(self.model, trajectory).states


@dataclass(frozen=True)
class TruePositionTracker:
    """The true pose as the state: the upper bound of the RL step. The pose is ``(x, y)``,
    or in ``drive`` ``(x, y, cos, sin)`` of the heading (``sim_node.env.pose_of``)."""

    representation: str = TRUE_POSITION
    fingerprint: str = TRUE_POSITION
    sees_images: bool = False

    def start(self, image: np.ndarray, position: np.ndarray) -> np.ndarray:
        """The true start pose."""
        return np.asarray(position, dtype=np.float64).copy()

    def step(
        self, state: np.ndarray, action: int, image: np.ndarray, position: np.ndarray
    ) -> np.ndarray:
        """The true pose after the step."""
        return np.asarray(position, dtype=np.float64).copy()

    def track(self, trajectory: Trajectory) -> np.ndarray:
        """The recorded ground-truth positions."""
        if trajectory.positions is None:
            raise DataError("the true-position baseline needs /ground_truth/pose in the bag")
        return np.asarray(trajectory.positions, dtype=np.float64)


def load_tracker(spec: str | Path | ModelFile) -> ModelTracker | TruePositionTracker:
    """``"true-position"`` for the baseline, an opened model file, or a model file's path."""
    if isinstance(spec, ModelFile):
        return ModelTracker(spec.model, spec.fingerprint)
    if str(spec) == TRUE_POSITION:
        return TruePositionTracker()
    return load_tracker(open_model(spec))
