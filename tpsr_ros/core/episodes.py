"""From rosbag2 bags to a trajectory of steps and to the episodes of guide section 3.1.

A *step* is one image and one action carrying the identical header stamp (DESIGN.md: step
k's messages are all stamped t_k; the log time is ignored). Steps are sorted by stamp and
split into *segments* of consecutive stamps (exactly ``step_ns`` apart): a gap, a step whose
image or action is missing, and a bag boundary each end a segment. Every segment is cut
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

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.io.bag import BagReader
from tpsr_ros.core.errors import BagError, ConfigError, DataError, MessageError
from tpsr_ros.io.messages import (
    ACTION_TYPE,
    IMAGE_TYPE,
    POSE_TYPE,
    REWARD_TYPE,
    image_to_array,
    pose_to_xy,
    reward_to_sample,
    stamp_of,
    twist_to_xy,
)
from tpsr_ros.core.state_model import StateModel, Track

__all__ = [
    "DEFAULT_ACTION_TOLERANCE",
    "DEFAULT_IMAGE_SHAPE",
    "STEP_NS",
    "Episodes",
    "Topics",
    "Trajectory",
    "image_to_observation",
    "images_to_observations",
    "make_episodes",
    "read_trajectory",
    "track_trajectory",
    "velocities_to_actions",
]

STEP_NS = 1_000_000_000
"""Duration of one step (DESIGN.md: 1 s of simulation time)."""
DEFAULT_IMAGE_SHAPE = (16, 16)
DEFAULT_ACTION_TOLERANCE = 1.0
"""Largest distance (m/s, per component) of a velocity from its action; half the spacing is 1.5."""


@dataclass(frozen=True)
class Topics:
    """Topic names read from bags (defaults from DESIGN.md)."""

    image: str = field(default="/camera/image_raw", metadata={"help": "camera image topic"})
    action: str = field(default="/action", metadata={"help": "executed action topic"})
    pose: str = field(default="/ground_truth/pose", metadata={"help": "ground-truth pose topic"})
    reward: str = field(default="/reward", metadata={"help": "reward topic"})

    def types(self) -> dict[str, str]:
        """Topic name to expected ROS type."""
        return {
            self.image: IMAGE_TYPE,
            self.action: ACTION_TYPE,
            self.pose: POSE_TYPE,
            self.reward: REWARD_TYPE,
        }


def image_to_observation(rgb: np.ndarray) -> np.ndarray:
    """Convert an ``(H, W, 3)`` uint8 image to the observation ``(H*W*3,)`` float64 in [0, 1]."""
    arr = np.asarray(rgb)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise MessageError(
            f"an observation image must be (H, W, 3) uint8, got {arr.shape} {arr.dtype}"
        )
    return arr.reshape(-1).astype(np.float64) / 255.0


def images_to_observations(images: np.ndarray) -> np.ndarray:
    """Convert ``(T, H, W, 3)`` uint8 images to observations ``(T, H*W*3)`` (one conversion)."""
    arr = np.asarray(images)
    if arr.dtype != np.uint8 or arr.ndim != 4 or arr.shape[3] != 3:
        raise MessageError(f"images must be (T, H, W, 3) uint8, got {arr.shape} {arr.dtype}")
    return arr.reshape(arr.shape[0], -1).astype(np.float64) / 255.0


def velocities_to_actions(
    velocities: np.ndarray, tolerance: float = DEFAULT_ACTION_TOLERANCE
) -> np.ndarray:
    """Map velocities ``(T, 2)`` to action indices ``(T,)``: the nearest of the 25 pairs."""
    from tpsr_ros.core.actions import action_indices

    vel = np.asarray(velocities, dtype=np.float64).reshape(-1, 2)
    try:
        return np.asarray(action_indices(vel, tolerance), dtype=np.int64)
    except ConfigError as exc:
        raise DataError(f"an action cannot be mapped to the 25 velocity pairs: {exc}") from None


def _n_actions() -> int:
    from tpsr_ros.core.actions import NUM_ACTIONS

    return int(NUM_ACTIONS)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Steps read from one or more bags, in stamp order (bags in the order given).

    Attributes:
        stamps: ``(T,)`` int64 header stamps (ns).
        observations: ``(T, k)`` float64, see :func:`image_to_observation`.
        actions: ``(T,)`` int64 action indices.
        velocities: ``(T, 2)`` commanded velocities as recorded.
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

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

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
            "environment": _common(s.get("environment") for s in self.sources),
            "image_shape": list(self.image_shape),
        }


def _common(values: Iterable[Any]) -> Any:
    distinct = {v for v in values}
    return distinct.pop() if len(distinct) == 1 else sorted(map(str, distinct))


def _bag_custom_data(reader: BagReader) -> tuple[str | None, Any]:
    """Environment name and generator settings that ``sim_node.generate`` stores in a bag."""
    custom = getattr(reader, "custom_data", None)
    if not isinstance(custom, dict):
        return None, None
    env = custom.get("tpsr_ros.environment")
    try:
        generator = json.loads(custom["tpsr_ros.generator"])
    except (KeyError, TypeError, ValueError):
        generator = None
    return (str(env) if env else None), generator


def _read_bag(
    path: Path, topics: Topics, image_shape: tuple[int, int] | None, require_ground_truth: bool
) -> dict[str, Any]:
    wanted = topics.types()
    with BagReader(path) as reader:
        counts = reader.message_counts
        available = {t: ty for t, ty in reader.topics.items() if counts.get(t, 0) > 0}
        required = [topics.image, topics.action]
        if require_ground_truth:
            required += [topics.pose, topics.reward]
        if missing := [t for t in required if t not in available]:
            raise BagError(
                f"bag {str(path)!r} has no messages on topic(s) {missing} (it has "
                f"{sorted(available)})"
            )
        for topic, msgtype in wanted.items():
            if topic in available and available[topic] != msgtype:
                raise BagError(
                    f"topic {topic!r} of bag {str(path)!r} has type {available[topic]}, "
                    f"expected {msgtype}"
                )
        data: dict[str, dict[int, Any]] = {t: {} for t in wanted}
        for bag_msg in reader.messages([t for t in wanted if t in available]):
            msg = bag_msg.decode()
            stamp = stamp_of(msg)
            if stamp in data[bag_msg.topic]:
                raise BagError(
                    f"bag {str(path)!r} has two messages on {bag_msg.topic!r} with stamp {stamp} ns"
                )
            try:
                if bag_msg.topic == topics.image:
                    value: Any = image_to_array(msg, shape=image_shape)
                    image_shape = image_shape or value.shape[:2]
                elif bag_msg.topic == topics.action:
                    value = twist_to_xy(msg)
                elif bag_msg.topic == topics.pose:
                    value = pose_to_xy(msg)
                else:
                    value = reward_to_sample(msg).reward
                if bag_msg.topic != topics.image and not np.isfinite(value).all():
                    raise MessageError(f"value {value} is not finite")
            except MessageError as exc:
                raise MessageError(
                    f"bag {str(path)!r}, topic {bag_msg.topic!r} at stamp {stamp} ns: {exc}"
                ) from None
            data[bag_msg.topic][stamp] = value
        environment, generator = _bag_custom_data(reader)
    return {
        "data": data,
        "environment": environment,
        "generator": generator,
        "image_shape": image_shape,
    }


def read_trajectory(
    bags: Sequence[Path | str],
    *,
    topics: Topics | None = None,
    image_shape: tuple[int, int] | None = DEFAULT_IMAGE_SHAPE,
    step_ns: int = STEP_NS,
    action_tolerance: float = DEFAULT_ACTION_TOLERANCE,
    require_ground_truth: bool = False,
) -> Trajectory:
    """Read and pair the steps of ``bags`` (see the module docstring).

    ``image_shape=None`` accepts any size, but all images must share it.
    ``require_ground_truth`` also demands the pose and reward topics.
    """
    topics = topics or Topics()
    if not bags:
        raise ConfigError("no bag given")
    if step_ns <= 0:
        raise ConfigError(f"step duration must be positive, not {step_ns} ns")
    parts: list[dict[str, np.ndarray]] = []
    sources: list[dict[str, Any]] = []
    shape = image_shape
    segment_offset = 0
    for bag in bags:
        path = Path(bag)
        read = _read_bag(path, topics, shape, require_ground_truth)
        shape = read["image_shape"]
        data = read["data"]
        images, actions = data[topics.image], data[topics.action]
        stamps = np.array(sorted(set(images) & set(actions)), dtype=np.int64)
        if stamps.size == 0:
            raise DataError(
                f"bag {str(path)!r} has no image and action with the same stamp "
                f"({len(images)} images, {len(actions)} actions)"
            )
        velocities = np.array([actions[s] for s in stamps], dtype=np.float64)
        obs = images_to_observations(np.stack([images[s] for s in stamps]))
        nan2 = (float("nan"), float("nan"))
        positions = np.array([data[topics.pose].get(s, nan2) for s in stamps], dtype=np.float64)
        rewards = np.array([data[topics.reward].get(s, np.nan) for s in stamps], dtype=np.float64)
        if require_ground_truth and (np.isnan(positions).any() or np.isnan(rewards).any()):
            raise DataError(f"bag {str(path)!r} lacks ground truth (pose or reward) for some steps")
        breaks = np.diff(stamps) != step_ns
        segments = segment_offset + np.concatenate([[0], np.cumsum(breaks)])
        segment_offset = int(segments[-1]) + 1
        parts.append(
            {
                "stamps": stamps,
                "observations": obs,
                "actions": velocities_to_actions(velocities, action_tolerance),
                "velocities": velocities,
                "positions": positions,
                "rewards": rewards,
                "segments": segments.astype(np.int64),
            }
        )
        sources.append(
            {
                "path": str(path),
                "steps": int(stamps.size),
                "segments": int(breaks.sum()) + 1,
                "unpaired_messages": int(len(images) + len(actions) - 2 * stamps.size),
                "stamps_ns": [int(stamps[0]), int(stamps[-1])],
                "environment": read["environment"],
                "generator": read["generator"],
                "topics": {
                    "image": topics.image,
                    "action": topics.action,
                    "pose": topics.pose,
                    "reward": topics.reward,
                },
            }
        )
    merged = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    assert shape is not None
    return Trajectory(
        **merged,
        image_shape=(int(shape[0]), int(shape[1])),
        n_actions=_n_actions(),
        sources=sources,
    )


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

    def __len__(self) -> int:
        return int(self.action.shape[0])

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
) -> Episodes:
    """Cut each segment into episodes of ``m + 1 + n`` consecutive steps up to ``max_episodes``."""
    m, n = int(history_length), int(test_length)
    if m < 1 or n < 1:
        raise ConfigError(f"history and test lengths must be at least 1, not {m} and {n}")
    if max_episodes is not None and max_episodes < 1:
        raise ConfigError(f"the number of episodes must be at least 1, not {max_episodes}")
    span = m + 1 + n
    starts = [
        np.arange(start, stop - span + 1, span, dtype=np.int64)
        for start, stop in trajectory.segment_bounds()
    ]
    first = np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)
    if max_episodes is not None:
        first = first[:max_episodes]
    if first.size == 0:
        raise DataError(
            f"no usable episodes: no run of {span} consecutive steps (history {m} + current + "
            f"test {n}) in {len(trajectory)} steps ({len(trajectory.segment_bounds())} segments)"
        )
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
