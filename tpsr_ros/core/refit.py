"""One TPSR fit of a whole trajectory as ``learner fit`` makes it, for a first fit and a refit.

``learner fit BAG`` (in memory), ``learner fit BAG --init-from MODEL`` and the learner node
all fit through :func:`fit_trajectory`, so the node's model after ``T`` live steps equals the
command's on a recording of those steps: the episodes cut from every step, the preset
sized to the data (a first fit) or the frozen basis of an earlier fit (a refit:
:mod:`tpsr_ros.core.fit_basis`), the refinement the config asks for, then the training
states tracked once for the viewer's read-outs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from tpsr_ros.core.episodes import Episodes, Trajectory, make_episodes, track_trajectory
from tpsr_ros.core.fit_basis import FitBasis
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.state_model import Track
from tpsr_ros.core.tpsr import Progress, TPSRConfig, TPSRModel
from tpsr_ros.core.view_readout import ViewReadout, fit_view_readout

__all__ = ["TrajectoryFit", "fit_trajectory", "view_of_track"]


@dataclass(frozen=True, eq=False)
class TrajectoryFit:
    """A fitted model, its training states, the viewer's read-outs and what the fit took."""

    model: TPSRModel
    tracked: Track
    view: ViewReadout
    episodes: int
    seconds: float

    def training(self, trajectory: Trajectory) -> dict[str, Any]:
        """The model file's description of its training data (as ``learner fit`` writes it)."""
        cfg = self.model.config
        return {
            **trajectory.summary(),
            "episodes": self.episodes,
            "history_length": cfg.history_length,
            "test_length": cfg.test_length,
            "fit_seconds": round(self.seconds, 6),
        }


def fit_trajectory(
    trajectory: Trajectory,
    config: TPSRConfig,
    *,
    basis: FitBasis | None = None,
    sizing: Sizing | None = None,
    action_codes: np.ndarray | None = None,
    pose_frame: str = "map",
    progress: Progress | None = None,
    episodes: Episodes | None = None,
    max_episodes: int | None = None,
) -> TrajectoryFit:
    """Fit ``trajectory`` with ``config`` (sized by ``sizing``), or refit it on ``basis``
    (then ``config`` is the basis's and only the rank rule applies); track its steps once.

    ``action_codes``: a robot model's codebook commands (action-aware features);
    ``pose_frame``: the frame of the training poses, for the decoded pose; ``episodes``:
    the trajectory's episodes when already cut (at most ``max_episodes`` of them).
    """
    start = time.perf_counter()
    cfg = basis.config if basis is not None else config
    if episodes is None:
        episodes = make_episodes(
            trajectory, cfg.history_length, cfg.test_length, max_episodes=max_episodes,
            stride=cfg.episode_stride,
        )  # fmt: skip
    model = fit_tpsr_trajectory(
        trajectory, cfg, episodes=episodes, max_episodes=max_episodes, progress=progress,
        sizing=Sizing() if basis is not None else sizing,
        action_codes=action_codes, basis=basis,
    )  # fmt: skip
    seconds = time.perf_counter() - start
    tracked = track_trajectory(model, trajectory)
    view = view_of_track(tracked, trajectory, pose_frame)
    return TrajectoryFit(model, tracked, view, len(episodes), seconds)


def view_of_track(tracked: Track, trajectory: Trajectory, pose_frame: str) -> ViewReadout:
    """The viewer's read-outs (next image, pose, state map) on a trajectory's tracked states."""
    positions = trajectory.positions
    return fit_view_readout(
        tracked.states,
        trajectory.actions,
        trajectory.observations,
        trajectory.segments,
        trajectory.n_actions,
        positions=positions if np.isfinite(positions).any() else None,
        pose_frame=pose_frame,
    )
