"""What a person can look at in a state: the next image it predicts, the pose it encodes.

A predictive state is worth having because it predicts; a vector of numbers does not show
that. :func:`fit_view_readout` learns, on the training data the model was fitted on, affine
read-outs of the tracked state ``b_k``:

- the next observation ``o_{k+1}`` for each action ``a_{k+1}`` (ridge regression of the
  observations that followed each action on ``[b_k, 1]``), and without an action, the
  action-blind map (all pairs pooled): what the model expects to see next;
- the pose at step k where the training data carry one (the affine decoding the guide uses
  to judge a state, section 4.3);
- the leading three principal directions of the training states, scaled to unit spread, so
  a viewer can draw the states as points in 3-D (the map the model learned).

The read-outs are plain linear algebra on states the model already tracks: they leave the
model, its fingerprint and every policy untouched.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tpsr_ros.core.errors import DataError, ModelFormatError

__all__ = ["VIEW_POINTS", "ViewReadout", "fit_view_readout", "next_step_pairs"]

VIEW_POINTS = 1000
"""Training states kept for the viewer's point cloud (evenly spaced over the data)."""
RIDGE = 1e-6
"""Ridge of every read-out, relative to the mean diagonal of its Gram matrix."""


@dataclass(frozen=True, eq=False)
class ViewReadout:
    """Affine read-outs of a model's state (module docstring).

    Attributes:
        image: ``(n_actions + 1, r + 1, k)``: ``[b, 1] @ image[a]`` is the expected next
            observation after action ``a``; ``image[n_actions]`` the action-blind one.
        pose: ``(r + 1, p)`` affine decoding of the pose (``p`` = 2: x, y; 4: also the
            heading's cosine and sine), or None when the training data had no pose.
        axes: ``(r, 3)`` leading principal directions of the training states, each divided
            by the spread along it: ``(b - center) @ axes`` has unit spread per coordinate.
        center: ``(r,)`` mean training state.
        points: ``(n, 3)`` training states in those coordinates (the viewer's map).
        pose_frame: frame of the decoded pose (the training pose topic's).

    """

    image: np.ndarray
    pose: np.ndarray | None
    axes: np.ndarray
    center: np.ndarray
    points: np.ndarray
    pose_frame: str = "map"

    def __post_init__(self) -> None:
        r = self.center.shape[0]
        if self.image.ndim != 3 or self.image.shape[1] != r + 1 or self.image.shape[0] < 2:
            raise ModelFormatError(f"view image read-out of shape {self.image.shape} for r={r}")
        if self.axes.shape != (r, 3) or self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ModelFormatError(
                f"view axes {self.axes.shape} / points {self.points.shape} for r={r}"
            )
        pose = self.pose
        if pose is not None and (pose.shape[0] != r + 1 or pose.shape[1] not in (2, 4)):
            raise ModelFormatError(f"view pose read-out of shape {self.pose.shape} for r={r}")

    @property
    def n_actions(self) -> int:
        """Number of actions (the action-blind read-out not counted)."""
        return self.image.shape[0] - 1

    @property
    def obs_size(self) -> int:
        """Values per observation."""
        return self.image.shape[2]

    def predicted_observation(self, state: np.ndarray, action: int | None) -> np.ndarray:
        """Expected next observation ``(k,)`` after ``action`` (None: action-blind)."""
        index = self.n_actions if action is None else action
        weights = self.image[index]
        return state @ weights[:-1] + weights[-1]

    def decoded_pose(self, state: np.ndarray) -> np.ndarray | None:
        """The pose ``(p,)`` read out of ``state`` (None without a pose read-out)."""
        if self.pose is None:
            return None
        return state @ self.pose[:-1] + self.pose[-1]

    def view_point(self, state: np.ndarray) -> np.ndarray:
        """``state`` in the viewer's three unit-spread coordinates ``(3,)``."""
        return (state - self.center) @ self.axes

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The arrays a model file stores (names prefixed ``view_``)."""
        arrays = {
            "view_image": self.image,
            "view_axes": self.axes,
            "view_center": self.center,
            "view_points": self.points,
        }
        if self.pose is not None:
            arrays["view_pose"] = self.pose
        return arrays


def next_step_pairs(segments: np.ndarray) -> np.ndarray:
    """Indices k whose next step k + 1 lies in the same segment (a state and what follows)."""
    segments = np.asarray(segments)
    return np.flatnonzero(segments[1:] == segments[:-1])


def _ridge_solve(design: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Least squares ``design @ W ~ targets`` with a small relative ridge (never singular)."""
    gram = design.T @ design
    scale = max(float(np.trace(gram)) / gram.shape[0], np.finfo(float).tiny)
    gram[np.diag_indices_from(gram)] += RIDGE * scale
    return np.linalg.solve(gram, design.T @ targets)


def _principal_axes(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and the three leading directions of ``states`` scaled to unit spread (missing
    directions of a state of fewer than three dimensions, or of no spread, are zero)."""
    center = states.mean(axis=0)
    _, singular, vt = np.linalg.svd(states - center, full_matrices=False)
    spread = singular / np.sqrt(max(len(states) - 1, 1))
    axes = np.zeros((states.shape[1], 3))
    keep = min(3, len(spread))
    tiny = max(float(spread[0]) if len(spread) else 0.0, 1.0) * 1e-12
    for i in range(keep):
        if spread[i] > tiny:
            axes[:, i] = vt[i] / spread[i]
    return center, axes


def fit_view_readout(
    states: np.ndarray,
    actions: np.ndarray,
    observations: np.ndarray,
    segments: np.ndarray,
    n_actions: int,
    *,
    positions: np.ndarray | None = None,
    pose_frame: str = "map",
    max_points: int = VIEW_POINTS,
) -> ViewReadout:
    """Fit the read-outs on tracked training states (module docstring).

    ``states[k]`` is the state after step k of a trajectory whose step k has action
    ``actions[k]`` and observation ``observations[k]``; steps of one ``segments`` value are
    consecutive. An action seen fewer than ``r + 2`` times before a next step takes the
    action-blind read-out. ``positions`` ``(T, 2 | 4)`` (NaN where unknown) adds the pose.
    """
    states = np.asarray(states, dtype=np.float64)
    t, r = states.shape
    pairs = next_step_pairs(segments)
    if len(pairs) < r + 2:
        raise DataError(
            f"{len(pairs)} consecutive step pairs cannot fit a read-out of a {r}-d state"
        )
    design = np.concatenate([states[pairs], np.ones((len(pairs), 1))], axis=1)
    following = np.asarray(observations, dtype=np.float64)[pairs + 1]
    next_actions = np.asarray(actions)[pairs + 1]
    pooled = _ridge_solve(design, following)
    image = np.repeat(pooled[None], n_actions + 1, axis=0)
    for action in np.unique(next_actions):  # one solve per action, never per step
        mask = next_actions == action
        if 0 <= action < n_actions and mask.sum() >= r + 2:
            image[action] = _ridge_solve(design[mask], following[mask])
    pose = None
    if positions is not None:
        positions = np.asarray(positions, dtype=np.float64)
        known = np.isfinite(positions).all(axis=1)
        if known.sum() >= r + 2:
            with_one = np.concatenate([states[known], np.ones((int(known.sum()), 1))], axis=1)
            pose = _ridge_solve(with_one, positions[known])
    center, axes = _principal_axes(states)
    keep = np.unique(np.linspace(0, t - 1, min(max_points, t)).round().astype(np.int64))
    points = (states[keep] - center) @ axes
    return ViewReadout(image, pose, axes, center, points, pose_frame)
