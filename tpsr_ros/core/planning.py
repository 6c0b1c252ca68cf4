"""Fitted Q on tracked states: transitions, the planner's predictive targets, the ridge ladder.

The ROS-free part of ``learner policy`` (and of the learner node's refits): the states a
model tracked over a trajectory with rewards become transitions ``(s_k, a_{k+1}, r_{k+1},
s_{k+1})`` that never cross a gap, and :func:`fit_q_on` runs fitted Q-iteration on them,
refitting at a larger ridge when it diverges. For ``fqi.state_scaling=predictive`` the
planner weighs state directions by what they predict: the future targets of ``learner
tune``'s criterion (:class:`ObservationFeatures`, :func:`future_targets`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.fqi import MAX_RIDGE, FQIConfig, QFunction, fit_q, ridge_ladder
from tpsr_ros.core.whitening import Whitening

__all__ = [
    "FUTURE_FEATURES",
    "FUTURE_HORIZONS",
    "MAX_RIDGE",
    "MissingRewards",
    "ObservationFeatures",
    "fit_q_on",
    "future_pairs",
    "future_targets",
    "ridge_ladder",
    "transitions",
]

FUTURE_HORIZONS = 10
"""Future steps predicted: the planner's horizon ``1 / (1 - 0.9)``."""
FUTURE_FEATURES = 10
"""Principal components of the observations predicted at each future step."""


class MissingRewards(DataError):
    """Transitions lack the reward of the step they lead to (the caller says where to get them)."""


@dataclass(frozen=True)
class ObservationFeatures:
    """Fixed targets: the top principal components of a trajectory's raw observations."""

    pca: Whitening

    @classmethod
    def fit(cls, observations: np.ndarray, dim: int) -> ObservationFeatures:
        """PCA of ``observations (T, k)`` keeping ``dim`` components (all ``k`` if fewer)."""
        kept = min(dim, observations.shape[1])
        return cls(Whitening.fit(observations, kept, what="observations for tuning targets"))

    def transform(self, observations: np.ndarray) -> np.ndarray:
        """Component scores ``(T, d)`` of the ``d`` components kept (not whitened)."""
        scores: np.ndarray = (observations - self.pca.mean_) @ self.pca.components_
        return scores


def future_targets(
    features: np.ndarray, segments: np.ndarray, horizons: int
) -> tuple[np.ndarray, np.ndarray]:
    """Targets ``(T, horizons, d)``: row ``s`` holds the features of steps ``s+1..s+k``.

    Returns the targets and a ``(T,)`` mask of rows whose ``k`` future steps all lie in
    the same segment (the rest hold zeros).
    """
    n, d = features.shape
    targets = np.zeros((n, horizons, d))
    valid = np.zeros(n, dtype=bool)
    if n > horizons:
        valid[: n - horizons] = segments[horizons:] == segments[: n - horizons]
        for j in range(1, horizons + 1):
            targets[: n - j, j - 1] = features[j:]
    return targets, valid


def transitions(
    states: np.ndarray, trajectory: Trajectory, *, skip_unknown: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(s_k, a_{k+1}, r_{k+1}, s_{k+1})`` for consecutive steps of each segment.

    A step without a reward (NaN) is refused, or with ``skip_unknown`` its transition is
    left out (a goal region's steps beyond the poses recorded); none left is refused.
    """
    if len(states) != len(trajectory):
        raise DataError(f"{len(states)} states for {len(trajectory)} steps")
    current = np.concatenate(
        [np.arange(a, b - 1) for a, b in trajectory.segment_bounds() if b - a > 1] or [[]]
    ).astype(np.int64)
    following = current + 1
    known = np.isfinite(trajectory.rewards[following])
    if not known.all():
        if not skip_unknown or not known.any():
            raise MissingRewards(
                f"the RL data lacks rewards for {int((~known).sum())} of {known.size} "
                "transitions; rewards are needed to plan"
            )
        current, following = current[known], following[known]
    rewards = trajectory.rewards[following]
    return states[current], trajectory.actions[following], rewards, states[following]


def future_pairs(states: np.ndarray, trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """States paired with the principal components of the observations that followed them.

    For ``fqi.state_scaling=predictive``: the top :data:`FUTURE_FEATURES` components of
    the trajectory's observations at each of the next :data:`FUTURE_HORIZONS` steps,
    within a segment, so the planner weighs state directions by what they predict.
    """
    pca = ObservationFeatures.fit(trajectory.observations, FUTURE_FEATURES)
    targets, valid = future_targets(
        pca.transform(trajectory.observations), trajectory.segments, FUTURE_HORIZONS
    )
    return states[valid], targets[valid].reshape(int(valid.sum()), -1)


def fit_q_on(
    states: np.ndarray, trajectory: Trajectory, config: FQIConfig, *, skip_unknown: bool = False
) -> tuple[QFunction, FQIConfig, int]:
    """Fitted Q on the transitions of ``states`` tracked over ``trajectory``.

    A fit that diverges is refitted at the next ridge of :func:`ridge_ladder`: all of it,
    or with ``config.refit == "member"`` only the ensemble members that diverged
    (``QFunction.ridges`` records each member's). Returns the Q-function, the
    configuration that fitted it (its ridge the largest any member needed) and the number
    of transitions; raises ``DivergenceError`` when every ridge diverges. ``skip_unknown``:
    see :func:`transitions`.
    """
    s, a, r, s_next = transitions(states, trajectory, skip_unknown=skip_unknown)
    futures = future_pairs(states, trajectory) if config.state_scaling == "predictive" else None
    q = fit_q(s, a, r, s_next, trajectory.n_actions, config, futures=futures, max_ridge=MAX_RIDGE)
    return q, dataclasses.replace(config, ridge=max(q.ridges or (config.ridge,))), len(a)
