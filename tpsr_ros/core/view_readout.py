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

from dataclasses import dataclass, field

import numpy as np

from tpsr_ros.core.errors import DataError, ModelFormatError
from tpsr_ros.core.moments import Moments
from tpsr_ros.core.tpsr_stages import action_sums
from tpsr_ros.core.whitening import covariance_eigenpairs, flip_signs

__all__ = [
    "VIEW_POINTS",
    "ViewReadout",
    "ViewSums",
    "fit_view_readout",
    "next_step_pairs",
    "point_rows",
]

VIEW_POINTS = 1000
"""Training states kept for the viewer's point cloud (evenly spaced over the data)."""
RIDGE = 1e-6
"""Ridge of every read-out, relative to the mean diagonal of its Gram matrix."""
FLAT = 1e-6
"""A state direction whose spread is below this fraction of the largest is drawn flat."""


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


def _ridge_solve(gram: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """``W`` of the normal equations ``gram W = cross`` with a small relative ridge (never
    singular)."""
    gram = gram.copy()
    scale = max(float(np.trace(gram)) / gram.shape[0], np.finfo(float).tiny)
    gram[np.diag_indices_from(gram)] += RIDGE * scale
    return np.linalg.solve(gram, cross)


def _with_one(states: np.ndarray) -> np.ndarray:
    return np.concatenate([states, np.ones((states.shape[0], 1))], axis=1)


@dataclass
class ViewSums:
    """The read-outs' sufficient statistics, added chunk by chunk and merged across
    workers, then solved once (:meth:`solve`): a fit over more steps than memory holds.

    ``add`` takes a chunk of tracked steps; the pair of a chunk's last step and the next
    chunk's first (same segment) is counted by passing the previous chunk's last state and
    segment as ``before``.
    """

    n_actions: int
    state_dim: int
    obs_size: int
    pose_dim: int = 0
    image_gram: np.ndarray = field(init=False)
    image_cross: np.ndarray = field(init=False)
    image_pairs: np.ndarray = field(init=False)
    pose_gram: np.ndarray = field(init=False)
    pose_cross: np.ndarray = field(init=False)
    states: Moments = field(init=False)

    def __post_init__(self) -> None:
        a, d, k = self.n_actions, self.state_dim + 1, self.obs_size
        self.image_gram, self.image_cross = np.zeros((a, d, d)), np.zeros((a, d, k))
        self.image_pairs = np.zeros(a, dtype=np.int64)
        self.pose_gram, self.pose_cross = np.zeros((d, d)), np.zeros((d, max(self.pose_dim, 1)))
        self.states = Moments.empty(d - 1)

    def add(
        self,
        states: np.ndarray,
        actions: np.ndarray,
        observations: np.ndarray,
        segments: np.ndarray,
        positions: np.ndarray | None = None,
        before: tuple[np.ndarray, int] | None = None,
    ) -> None:
        """Count a chunk of steps (``before``: the previous chunk's last state and segment)."""
        states = np.asarray(states, dtype=np.float64)
        segments = np.asarray(segments)
        pairs = next_step_pairs(segments)
        design = _with_one(states[pairs])
        following = np.asarray(observations, dtype=np.float64)[pairs + 1]
        next_actions = np.asarray(actions, dtype=np.int64)[pairs + 1]
        if before is not None and len(segments) and segments[0] == before[1]:
            design = np.concatenate([_with_one(before[0][None]), design])
            following = np.concatenate([np.asarray(observations[:1], dtype=np.float64),
                                        following])  # fmt: skip
            next_actions = np.concatenate([np.asarray(actions[:1], dtype=np.int64), next_actions])
        counts = np.bincount(next_actions, minlength=self.n_actions)
        self.image_gram += action_sums(design, design, next_actions, counts)
        self.image_cross += action_sums(design, following, next_actions, counts)
        self.image_pairs += counts
        if positions is not None and self.pose_dim:
            known = np.isfinite(positions).all(axis=1)
            with_one = _with_one(states[known])
            self.pose_gram += with_one.T @ with_one
            self.pose_cross += with_one.T @ np.asarray(positions, dtype=np.float64)[known]
        self.states = self.states.merge(Moments.of(states))

    def merge(self, other: ViewSums) -> ViewSums:
        """The sums of both (the order of chunks never matters)."""
        merged = ViewSums(self.n_actions, self.state_dim, self.obs_size, self.pose_dim)
        for name in ("image_gram", "image_cross", "image_pairs", "pose_gram", "pose_cross"):
            setattr(merged, name, getattr(self, name) + getattr(other, name))
        merged.states = self.states.merge(other.states)
        return merged

    def solve(self, points: np.ndarray, pose_frame: str = "map") -> ViewReadout:
        """The read-outs; ``points`` ``(n, r)`` the training states drawn as the map."""
        r = self.state_dim
        if self.image_pairs.sum() < r + 2:
            raise DataError(
                f"{int(self.image_pairs.sum())} consecutive step pairs cannot fit a read-out "
                f"of a {r}-d state"
            )
        pooled = _ridge_solve(self.image_gram.sum(axis=0), self.image_cross.sum(axis=0))
        image = np.repeat(pooled[None], self.n_actions + 1, axis=0)
        for action in np.flatnonzero(self.image_pairs >= r + 2):
            image[action] = _ridge_solve(self.image_gram[action], self.image_cross[action])
        pose = None
        if self.pose_dim and self.pose_gram[-1, -1] >= r + 2:  # the count of known poses
            pose = _ridge_solve(self.pose_gram, self.pose_cross)
        center, axes = self._principal_axes()
        return ViewReadout(image, pose, axes, center, (points - center) @ axes, pose_frame)

    def _principal_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean and the three leading directions of the states scaled to unit spread (signs
        as :func:`~tpsr_ros.core.whitening.flip_signs` sets them; missing ones, and flat
        ones, of less than :data:`FLAT` of the largest spread, zero: rounding, not
        structure)."""
        moments, r = self.states, self.state_dim
        cov = moments.scatter / max(moments.count - 1, 1)
        keep = min(3, r)
        values, vectors, _ = covariance_eigenpairs(cov, keep)
        (vectors,) = flip_signs(vectors[:, ::-1])  # largest first
        spread = np.sqrt(np.maximum(values[::-1], 0.0))
        flat = spread <= FLAT * spread[0]
        axes = np.zeros((r, 3))
        axes[:, :keep] = np.where(flat, 0.0, vectors / np.where(flat, 1.0, spread))
        return moments.mean, axes


def point_rows(total: int, max_points: int = VIEW_POINTS) -> np.ndarray:
    """The rows of ``total`` steps whose states the viewer draws: evenly spaced."""
    return np.unique(np.linspace(0, total - 1, min(max_points, total)).round().astype(np.int64))


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
    """Fit the read-outs on tracked training states held in memory (module docstring).

    ``states[k]`` is the state after step k of a trajectory whose step k has action
    ``actions[k]`` and observation ``observations[k]``; steps of one ``segments`` value are
    consecutive. An action seen fewer than ``r + 2`` times before a next step takes the
    action-blind read-out. ``positions`` ``(T, 2 | 4)`` (NaN where unknown) adds the pose.
    """
    states = np.asarray(states, dtype=np.float64)
    obs = np.asarray(observations, dtype=np.float64)
    pose_dim = 0 if positions is None else int(np.asarray(positions).shape[1])
    sums = ViewSums(n_actions, states.shape[1], obs.shape[1], pose_dim)
    sums.add(states, actions, obs, segments, positions)
    return sums.solve(states[point_rows(len(states), max_points)], pose_frame)
