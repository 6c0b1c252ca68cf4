"""Trajectories read from rosbag2 bags: the bag side of :mod:`tpsr_ros.core.episodes`.

A *step* is one image and one action carrying the identical header stamp (DESIGN.md: step
k's messages are all stamped t_k; the log time is ignored). Steps are sorted by stamp and
split into *segments* of consecutive stamps (exactly ``step_ns`` apart): a gap, a step whose
image or action is missing, and a bag boundary each end a segment. The pure part (the
:class:`~tpsr_ros.core.episodes.Trajectory` and how it is cut into episodes) is in
:mod:`tpsr_ros.core.episodes`.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.actions import NUM_ACTIONS
from tpsr_ros.core.episodes import (
    DEFAULT_ACTION_TOLERANCE,
    DEFAULT_IMAGE_SHAPE,
    STEP_NS,
    Trajectory,
    images_to_observations,
    velocities_to_actions,
)
from tpsr_ros.core.errors import BagError, ConfigError, DataError, MessageError
from tpsr_ros.io.bag import BagReader
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

__all__ = ["Topics", "read_trajectory"]


@dataclass(frozen=True)
class Topics:
    """Topic names read from bags (defaults from DESIGN.md)."""

    image: str = field(default="/camera/image_raw", metadata={"help": "camera image topic"})
    action: str = field(
        default="/action",
        metadata={"help": "executed action topic (TwistStamped; Twist too with --step-period)"},
    )
    pose: str = field(
        default="/ground_truth/pose",
        metadata={
            "help": "ground-truth pose topic (PoseStamped; with --step-period also Odometry, "
            "TransformStamped, PoseWithCovarianceStamped)"
        },
    )
    reward: str = field(default="/reward", metadata={"help": "reward topic"})

    def types(self) -> dict[str, str]:
        """Topic name to expected ROS type."""
        return {
            self.image: IMAGE_TYPE,
            self.action: ACTION_TYPE,
            self.pose: POSE_TYPE,
            self.reward: REWARD_TYPE,
        }


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
        n_actions=NUM_ACTIONS,
        sources=sources,
    )


# stand-in until issue18a lands
def iter_trajectory_chunks(
    bags: Sequence[Path | str],
    *,
    topics: Topics | None = None,
    image_shape: tuple[int, int] | None = DEFAULT_IMAGE_SHAPE,
    step_ns: int = STEP_NS,
    action_tolerance: float = DEFAULT_ACTION_TOLERANCE,
    require_ground_truth: bool = False,
    chunk_steps: int = 8192,
) -> Iterator[Trajectory]:
    """Yield the steps of ``bags`` as trajectories of at most ``chunk_steps`` steps.

    Their concatenation equals :func:`read_trajectory` (segments numbered globally; a bag
    boundary ends a segment); ``sources`` is empty except on each bag's last chunk.
    Stand-in: reads one whole bag at a time with :func:`read_trajectory` and slices it.
    """
    if chunk_steps < 1:
        raise ConfigError(f"chunk_steps must be at least 1, not {chunk_steps}")
    offset = 0
    for bag in bags:
        whole = read_trajectory(
            [bag],
            topics=topics,
            image_shape=image_shape,
            step_ns=step_ns,
            action_tolerance=action_tolerance,
            require_ground_truth=require_ground_truth,
        )
        segments = whole.segments + offset
        offset = int(segments[-1]) + 1
        for start in range(0, len(whole), chunk_steps):
            stop = min(start + chunk_steps, len(whole))
            yield Trajectory(
                stamps=whole.stamps[start:stop],
                observations=whole.observations[start:stop],
                actions=whole.actions[start:stop],
                velocities=whole.velocities[start:stop],
                positions=whole.positions[start:stop],
                rewards=whole.rewards[start:stop],
                segments=segments[start:stop],
                image_shape=whole.image_shape,
                n_actions=whole.n_actions,
                sources=whole.sources if stop == len(whole) else [],
            )
