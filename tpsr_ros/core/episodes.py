"""A trajectory of steps and the episodes of guide section 3.1 (numpy only).

A *trajectory* is a sequence of steps ``(a_k, o_k)`` split into *segments* of consecutive
stamps (exactly ``step_ns`` apart). It comes from bags (:func:`tpsr_ros.io.trajectory.
read_trajectory`: a gap, a step whose image or action is missing, and a bag boundary each
end a segment) or from arrays (:meth:`Trajectory.from_arrays`). Every segment is cut
from its start into non-overlapping *episodes* of ``m`` history steps, the current step and
``n`` test steps, and any remainder shorter than ``m + 1 + n`` is dropped, so no episode
spans a gap or two bags.

Observations are float64 vectors of ``H * W * 3`` values: the rgb8 pixels in row-major
``(height, width, channel)`` order divided by 255, so in ``[0, 1]``
(:func:`image_to_observation`). Whitening makes the learner insensitive to this scale, but
training, tracking and the filter node must all use this one function. Actions are the
indices of the nearest of the simulator's 25 velocity pairs (:mod:`tpsr_ros.core.actions`);
velocities farther than ``action_tolerance`` from every pair are refused. Ground truth
(position, reward) is carried alongside for plots and evaluation, never used for learning;
steps without it hold NaN.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tpsr_ros.core.actions import action_indices
from tpsr_ros.core.errors import ConfigError, DataError, MessageError
from tpsr_ros.core.images import Preprocessing, preprocess_images
from tpsr_ros.core.state_model import StateModel, Track
from tpsr_ros.core.units import STEP_NS

__all__ = [
    "DEFAULT_ACTION_TOLERANCE",
    "DEFAULT_IMAGE_SHAPE",
    "STEP_NS",
    "Episodes",
    "Trajectory",
    "episode_starts",
    "episodes_at",
    "image_to_observation",
    "images_to_observations",
    "make_episodes",
    "track_trajectory",
    "velocities_to_actions",
]

DEFAULT_IMAGE_SHAPE = (16, 16)
DEFAULT_ACTION_TOLERANCE = 1.0
"""Largest distance (m/s, per component) of a velocity from its action; half the spacing is 1.5."""


def image_to_observation(rgb: np.ndarray) -> np.ndarray:
    """Convert an ``(H, W, 3)`` uint8 image to the observation ``(H*W*3,)`` float64 in [0, 1]."""
    arr = np.asarray(rgb)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise MessageError(
            f"an observation image must be (H, W, 3) uint8, got {arr.shape} {arr.dtype}"
        )
    return images_to_observations(arr[None])[0]


def images_to_observations(images: np.ndarray) -> np.ndarray:
    """Convert ``(T, H, W, 3)`` uint8 images to observations ``(T, H*W*3)`` (one conversion).

    The identity case of :func:`tpsr_ros.core.images.preprocess_images` (pixels / 255).
    """
    arr = np.asarray(images)
    if arr.dtype != np.uint8 or arr.ndim != 4 or arr.shape[3] != 3:
        raise MessageError(f"images must be (T, H, W, 3) uint8, got {arr.shape} {arr.dtype}")
    return preprocess_images(arr, Preprocessing(arr.shape[1], arr.shape[2]))


def velocities_to_actions(
    velocities: np.ndarray, tolerance: float = DEFAULT_ACTION_TOLERANCE
) -> np.ndarray:
    """Map velocities ``(T, 2)`` to action indices ``(T,)``: the nearest of the 25 pairs."""
    vel = np.asarray(velocities, dtype=np.float64).reshape(-1, 2)
    try:
        return np.asarray(action_indices(vel, tolerance), dtype=np.int64)
    except ConfigError as exc:
        raise DataError(f"an action cannot be mapped to the 25 velocity pairs: {exc}") from None


STEP_FIELDS = (
    "stamps", "observations", "actions", "velocities", "positions", "rewards", "segments"
)
"""The per-step arrays of a :class:`Trajectory`, in field order."""


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Steps in stamp order, read from bags or built from arrays.

    :func:`tpsr_ros.io.trajectory.read_trajectory` reads bags (in the order given);
    :meth:`from_arrays` takes any action and observation arrays.

    Attributes:
        stamps: ``(T,)`` int64 header stamps (ns).
        observations: ``(T, k)`` float64, see :func:`image_to_observation`.
        actions: ``(T,)`` int64 action indices.
        velocities: ``(T, 2)`` commanded velocities as recorded (robot bags: ``(T, d)``, the
            command components of the action codebook).
        positions: ``(T, 2)`` true position (NaN where no pose has the step's stamp).
        rewards: ``(T,)`` reward (NaN where missing).
        segments: ``(T,)`` int64 segment number, increasing; consecutive stamps share one.
        image_shape: ``(H, W)`` of the images.
        n_actions: number of action indices.
        sources: one dict per bag: path, steps, segments, stamp range, environment, topics.

    """

    stamps: np.ndarray
    observations: np.ndarray
    actions: np.ndarray
    velocities: np.ndarray
    positions: np.ndarray
    rewards: np.ndarray
    segments: np.ndarray
    image_shape: tuple[int, int]
    n_actions: int
    sources: list[dict[str, Any]]

    @classmethod
    def from_arrays(
        cls,
        actions: np.ndarray,
        observations: np.ndarray,
        *,
        stamps: np.ndarray | None = None,
        n_actions: int | None = None,
        step_ns: int = STEP_NS,
        positions: np.ndarray | None = None,
        rewards: np.ndarray | None = None,
        image_shape: tuple[int, int] | None = None,
    ) -> Trajectory:
        """Build a trajectory of ``T`` steps from arrays: the front door for data not in bags.

        Args:
            actions: ``(T,)`` action indices ``a_k`` in ``0 .. n_actions - 1``.
            observations: ``(T, k)`` observation vectors ``o_k`` (any real features; images
                go through :func:`images_to_observations` first).
            stamps: ``(T,)`` int stamps (ns); default ``1, 2, ... T`` steps. A stamp that is
                not ``step_ns`` after the previous one starts a new segment (a gap).
            n_actions: number of actions (default ``max(actions) + 1``).
            step_ns: the step period (ns) that consecutive stamps are apart.
            positions: ``(T, 2)`` ground-truth positions, for plots only (default NaN).
            rewards: ``(T,)`` rewards, for planning only (default NaN).
            image_shape: ``(H, W)`` if the observations are rgb8 images (default ``(1, k)``).

        """
        obs = np.asarray(observations, dtype=np.float64)
        if obs.ndim != 2 or obs.shape[0] == 0:
            raise DataError(f"observations must be a non-empty (T, k) array, got {obs.shape}")
        n_steps = obs.shape[0]
        acts = np.asarray(actions)
        if acts.shape != (n_steps,) or acts.dtype.kind not in "iu":
            raise DataError(
                f"actions must be {n_steps} integer indices, got {acts.dtype} {acts.shape}"
            )
        acts = acts.astype(np.int64)
        count = int(acts.max()) + 1 if n_actions is None else int(n_actions)
        if acts.min() < 0 or acts.max() >= count:
            raise DataError(f"action indices must lie in 0..{count - 1}")
        if stamps is None:
            stamp_arr = np.arange(1, n_steps + 1, dtype=np.int64) * int(step_ns)
        else:
            stamp_arr = np.asarray(stamps, dtype=np.int64)
            if stamp_arr.shape != (n_steps,) or np.any(np.diff(stamp_arr) <= 0):
                raise DataError(f"stamps must be {n_steps} increasing integers (ns)")
        segments = np.concatenate([[0], np.cumsum(np.diff(stamp_arr) != step_ns)])
        nan = np.full(n_steps, np.nan)
        truth = np.column_stack([nan, nan]) if positions is None else positions
        return cls(
            stamps=stamp_arr,
            observations=obs,
            actions=acts,
            velocities=np.full((n_steps, 2), np.nan),
            positions=np.asarray(truth, dtype=np.float64),
            rewards=nan if rewards is None else np.asarray(rewards, dtype=np.float64),
            segments=segments.astype(np.int64),
            image_shape=image_shape or (1, obs.shape[1]),
            n_actions=count,
            sources=[],
        )

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def rows(self, start: int, stop: int) -> Trajectory:
        """Steps ``[start, stop)``, without ``sources`` (they describe whole bags)."""
        part = slice(start, stop)
        return replace(self, sources=[], **{n: getattr(self, n)[part] for n in STEP_FIELDS})

    def segment_bounds(self) -> list[tuple[int, int]]:
        """``[start, stop)`` row ranges of the segments."""
        if len(self) == 0:
            return []
        cuts = np.flatnonzero(np.diff(self.segments)) + 1
        starts = np.concatenate([[0], cuts])
        stops = np.concatenate([cuts, [len(self)]])
        return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]

    def summary(self) -> dict[str, Any]:
        """Training-data description for model metadata."""
        return {
            "bags": self.sources,
            "steps": len(self),
            "segments": len(self.segment_bounds()),
            "stamps_ns": [int(self.stamps[0]), int(self.stamps[-1])] if len(self) else [],
            "environment": common_value(s.get("environment") for s in self.sources),
            "vertical_half_extent": common_value(
                s.get("vertical_half_extent") for s in self.sources
            ),
            "image_shape": list(self.image_shape),
        }


def common_value(values: Iterable[Any]) -> Any:
    """The one value of ``values``, or their sorted texts when they differ (metadata)."""
    distinct = {v for v in values}
    return distinct.pop() if len(distinct) == 1 else sorted(map(str, distinct))


@dataclass(frozen=True, eq=False)
class Episodes:
    """Non-overlapping episodes (guide table 3.1), with the current step's ground truth.

    Attributes:
        history: ``(E, m k)`` observations of the ``m`` history steps, oldest first.
        observation: ``(E, k)`` current observation.
        action: ``(E,)`` current action index.
        test: ``(E, n k)`` observations of the ``n`` test steps.
        stamps: ``(E,)`` stamp of the current step.
        positions: ``(E, 2)`` true position at the current step.
        rewards: ``(E,)`` reward at the current step.
        history_length, test_length: ``m`` and ``n``.
        n_actions: number of action indices.
        history_actions: ``(E, m)`` action of each history step (the one that led to it).
        test_actions: ``(E, n)`` action of each test step.

    """

    history: np.ndarray
    observation: np.ndarray
    action: np.ndarray
    test: np.ndarray
    stamps: np.ndarray
    positions: np.ndarray
    rewards: np.ndarray
    history_length: int
    test_length: int
    n_actions: int
    history_actions: np.ndarray
    test_actions: np.ndarray

    def __len__(self) -> int:
        return int(self.action.shape[0])

    def take(self, index: np.ndarray) -> Episodes:
        """The episodes ``index`` (indices or a boolean mask), in that order."""
        per_episode = ("history", "observation", "action", "test", "stamps", "positions",
                       "rewards", "history_actions", "test_actions")  # fmt: skip
        return replace(self, **{name: getattr(self, name)[index] for name in per_episode})

    def steps(self) -> np.ndarray:
        """Every observation of the episodes once, ``(E (m + 1 + n), k)`` (for the PCA baseline)."""
        k = self.observation.shape[1]
        return np.concatenate(
            [
                self.history.reshape(-1, self.history_length, k),
                self.observation[:, None, :],
                self.test.reshape(-1, self.test_length, k),
            ],
            axis=1,
        ).reshape(-1, k)


def make_episodes(
    trajectory: Trajectory,
    history_length: int = 1,
    test_length: int = 1,
    *,
    max_episodes: int | None = None,
    stride: int | None = None,
) -> Episodes:
    """Cut each segment into episodes of ``m + 1 + n`` consecutive steps up to ``max_episodes``,
    one starting every ``stride`` steps (default ``m + 1 + n``: the guide's, not overlapping;
    1: every window of the data)."""
    m, n = int(history_length), int(test_length)
    if m < 1 or n < 1:
        raise ConfigError(f"history and test lengths must be at least 1, not {m} and {n}")
    if max_episodes is not None and max_episodes < 1:
        raise ConfigError(f"the number of episodes must be at least 1, not {max_episodes}")
    span = m + 1 + n
    if stride is not None and not 1 <= stride <= span:
        raise ConfigError(f"the episode stride must lie in 1..{span}, not {stride}")
    first = episode_starts(trajectory, span, stride)
    if max_episodes is not None:
        first = first[:max_episodes]
    if first.size == 0:
        where = f"{len(trajectory)} steps ({len(trajectory.segment_bounds())} segments)"
        raise no_usable_episodes(m, n, where)
    return episodes_at(trajectory, first, m, n)


def no_usable_episodes(history_length: int, test_length: int, where: str) -> DataError:
    """The error for data with no run of steps long enough for one episode."""
    span = history_length + 1 + test_length
    return DataError(
        f"no usable episodes: no run of {span} consecutive steps (history {history_length} + "
        f"current + test {test_length}) in {where}"
    )


def episode_starts(trajectory: Trajectory, span: int, stride: int | None = None) -> np.ndarray:
    """First rows of the episodes of ``span`` steps cut from the start of every segment, one
    every ``stride`` steps (default ``span``)."""
    step = span if stride is None else int(stride)
    starts = [
        np.arange(start, stop - span + 1, step, dtype=np.int64)
        for start, stop in trajectory.segment_bounds()
    ]
    return np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)


def episodes_at(trajectory: Trajectory, first: np.ndarray, m: int, n: int) -> Episodes:
    """Cut the episodes (history ``m``, current, test ``n``) whose first rows are ``first``."""
    obs = trajectory.observations
    k = obs.shape[1]
    current = first + m
    hist_idx = first[:, None] + np.arange(m)
    test_idx = current[:, None] + 1 + np.arange(n)
    return Episodes(
        history=obs[hist_idx].reshape(-1, m * k),
        observation=obs[current],
        action=trajectory.actions[current],
        test=obs[test_idx].reshape(-1, n * k),
        stamps=trajectory.stamps[current],
        positions=trajectory.positions[current],
        rewards=trajectory.rewards[current],
        history_length=m,
        test_length=n,
        n_actions=trajectory.n_actions,
        history_actions=trajectory.actions[hist_idx],
        test_actions=trajectory.actions[test_idx],
    )


def track_trajectory(model: StateModel, trajectory: Trajectory) -> Track:
    """States of ``model`` over every step of ``trajectory`` (``(T, state_dim)``).

    Tracking restarts from :meth:`StateModel.initial_state` at the start of every segment:
    across a gap or a bag boundary the steps in between are unknown, so the previous state
    would be stale.
    """
    if trajectory.observations.shape[1] != model.obs_size:
        raise DataError(
            f"the bag's observations have {trajectory.observations.shape[1]} values, the model "
            f"expects {model.obs_size} (another image size?)"
        )
    if trajectory.n_actions != model.n_actions:
        raise DataError(
            f"the bag maps actions to {trajectory.n_actions} indices, the model has "
            f"{model.n_actions}"
        )
    parts = [
        model.track(trajectory.actions[a:b], trajectory.observations[a:b])
        for a, b in trajectory.segment_bounds()
    ]
    return Track(*(np.concatenate(arrays) for arrays in zip(*parts, strict=True)))
