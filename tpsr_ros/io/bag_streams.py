"""One bag's timed streams, read once: image stamps, commands, poses and rewards.

:func:`read_bag_streams` reads a bag's camera, command, ground-truth and reward topics in
one pass, without decoding pixels: images are placed in time by their header stamps (or
log times where the stamp is zero) and decoded later, only where a step uses them
(:mod:`tpsr_ros.io.streams`). Commands are read whole; a ``TwistStamped``'s time is its
header stamp, an unstamped command's (``Twist``, or a zero stamp) the stamp of the next
image in the bag's order (:mod:`tpsr_ros.core.resample`), which the filter node reproduces
from the publishers' send order. Commands after the last image have no date and are left
out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.errors import BagError, ConfigError, MessageError
from tpsr_ros.core.resample import increasing
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.images import IMAGE_TYPES
from tpsr_ros.io.messages import (
    TWIST_TYPE,
    deserialize,
    header_stamp_ns,
    quaternion_heading,
    stamp_of,
    twist_components,
)
from tpsr_ros.io.reward_messages import REWARD_TYPES, decode_reward
from tpsr_ros.io.stream_spec import COMMAND_TYPES

__all__ = [
    "DEFAULT_POSE_FRAME",
    "POSE_TYPES",
    "TF_TYPE",
    "TRANSFORM_TYPE",
    "BagStreams",
    "fast_time",
    "pose_frame_id",
    "pose_planar",
    "read_bag_streams",
    "where",
]

TF_TYPE = "tf2_msgs/msg/TFMessage"
TRANSFORM_TYPE = "geometry_msgs/msg/TransformStamped"
DEFAULT_POSE_FRAME = "base_link"
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    TF_TYPE,
)


@dataclass
class BagStreams:
    """One bag's timed streams: image stamps (pixels decoded later, only where a step uses
    them), commands with their components, poses and rewards."""

    path: Path
    components: tuple[str, ...]  # the columns of ``commands``
    image_type: str
    action_type: str
    image_times: np.ndarray  # (I,) of the images kept (increasing)
    image_numbers: np.ndarray  # (I,) their message index on the topic
    command_times: np.ndarray  # (C,) header stamp, or (unstamped) the next image's stamp
    command_log_times: np.ndarray  # (C,) when each was logged
    commands: np.ndarray  # (C, len(components))
    pose_topic: str | None
    pose_type: str
    pose_times: np.ndarray  # sorted
    pose_data: list[bytes]  # CDR, decoded only around the step times
    pose_values: np.ndarray | None  # (P, 4) already decoded (tf: transforms of one frame)
    reward_topic: str | None  # None: no reward topic read (the bag has none of a reward type)
    reward_times: np.ndarray  # header stamp (JointState) or log time (std_msgs)
    rewards: np.ndarray
    environment: str | None
    dropped_images: int


def _time(msg: Any, log_time: int) -> int:
    """Header stamp, or the log time where the stamp is not positive (unset)."""
    stamp = stamp_of(msg)
    return stamp if stamp > 0 else int(log_time)


def pose_planar(msg: Any, msgtype: str) -> tuple[float, float, float, float]:
    """``(x, y, cos yaw, sin yaw)`` of a pose message: the position in the plane and the
    heading about z (from the orientation quaternion; a zero quaternion counts as none)."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        point, q = msg.transform.translation, msg.transform.rotation
    elif msgtype == "geometry_msgs/msg/PoseStamped":
        point, q = msg.pose.position, msg.pose.orientation
    else:
        point, q = msg.pose.pose.position, msg.pose.pose.orientation
    return (float(point.x), float(point.y), *quaternion_heading(q))


def where(path: Path, topic: str, index: int) -> str:
    return f"bag {str(path)!r}, topic {topic!r}, message {index}"


def _check_types(
    path: Path, available: dict[str, str], topic: str, allowed: Sequence[str], what: str
) -> str:
    if topic not in available:
        raise BagError(
            f"bag {str(path)!r} has no messages on the {what} topic {topic!r} (it has "
            f"{sorted(available)})"
        )
    if available[topic] not in allowed:
        raise BagError(
            f"topic {topic!r} of bag {str(path)!r} has type {available[topic]}; a {what} "
            f"topic must be one of {', '.join(allowed)}"
        )
    return available[topic]


def _read_streams(
    path: Path,
    *,
    image_topic: str,
    action_topic: str,
    pose_topic: str | None,
    reward_topic: str | None,
    components: tuple[str, ...],
    require_pose: bool,
    pose_frame: str = DEFAULT_POSE_FRAME,
) -> BagStreams:
    with BagReader(path) as reader:
        available = reader.topics_with_messages
        image_type = _check_types(path, available, image_topic, IMAGE_TYPES, "camera")
        action_type = _check_types(path, available, action_topic, COMMAND_TYPES, "command")
        wanted = [image_topic, action_topic]
        if pose_topic and (require_pose or pose_topic in available):
            _check_types(path, available, pose_topic, POSE_TYPES, "ground-truth pose")
            wanted.append(pose_topic)
        if reward_topic and available.get(reward_topic) in REWARD_TYPES:
            wanted.append(reward_topic)
        numbers = dict.fromkeys(wanted, 0)
        image_times: list[int] = []
        command_times: list[int] = []
        command_logs: list[int] = []
        commands: list[np.ndarray] = []
        pose_times: list[int] = []
        pose_data: list[bytes] = []
        tf_values: list[tuple[float, float, float, float]] = []
        is_tf = bool(pose_topic) and available.get(pose_topic or "") == TF_TYPE
        reward_times: list[int] = []
        rewards: list[float] = []
        types = {topic: available[topic] for topic in wanted}
        for topic, log_time, data in reader.raw_messages(wanted):
            index = numbers[topic]
            numbers[topic] += 1
            try:
                if topic == image_topic:  # placed in time now, decoded only if a step uses it
                    image_times.append(fast_time(data, log_time))
                elif topic == pose_topic and is_tf:  # the transforms to the pose frame
                    for transform in deserialize(data, TF_TYPE).transforms:
                        if transform.child_frame_id == pose_frame:
                            pose_times.append(_time(transform, log_time))
                            tf_values.append(pose_planar(transform, TRANSFORM_TYPE))
                elif topic == pose_topic:
                    pose_times.append(fast_time(data, log_time))
                    pose_data.append(data)
                elif topic == action_topic:
                    msg = deserialize(data, types[topic])
                    commands.append(twist_components(msg, components))
                    stamp = 0 if action_type == TWIST_TYPE else stamp_of(msg)
                    # unstamped: dated later by the next image (UNDATED: its position)
                    command_times.append(stamp if stamp > 0 else UNDATED - len(image_times))
                    command_logs.append(int(log_time))
                else:
                    time, value = decode_reward(data, types[topic], log_time)
                    reward_times.append(time)
                    rewards.append(value)
            except MessageError as exc:
                raise MessageError(f"{where(path, topic, index)}: {exc}") from None
        environment = reader.custom_data.get("tpsr_ros.environment") or None
    times = np.array(image_times, dtype=np.int64)
    keep = increasing(times)
    command_t, dated = _date_commands(np.array(command_times, dtype=np.int64), times, keep)
    command_log = np.array(command_logs, dtype=np.int64)[dated]
    command_t = command_t[dated]
    order = np.argsort(command_t, kind="stable")
    pose_t = np.array(pose_times, dtype=np.int64)
    pose_order = np.argsort(pose_t, kind="stable")
    return BagStreams(
        path=path,
        components=components,
        image_type=image_type,
        action_type=action_type,
        image_times=times[keep],
        image_numbers=np.flatnonzero(keep),
        command_times=command_t[order],
        command_log_times=command_log[order],
        commands=np.array(commands, dtype=np.float64).reshape(-1, len(components))[dated][order],
        pose_topic=pose_topic if pose_topic in wanted else None,
        pose_type=available.get(pose_topic or "", ""),
        pose_times=pose_t[pose_order],
        pose_data=[pose_data[i] for i in pose_order.tolist()] if pose_data else [],
        pose_values=(
            np.array(tf_values, dtype=np.float64).reshape(-1, 4)[pose_order] if is_tf else None
        ),
        reward_topic=reward_topic if reward_topic in wanted else None,
        reward_times=np.array(reward_times, dtype=np.int64),
        rewards=np.array(rewards, dtype=np.float64),
        environment=str(environment) if environment else None,
        dropped_images=int(times.size - keep.sum()),
    )


UNDATED = -(2**62)
"""Command times below this mark an unstamped command: ``UNDATED - n`` came after n images."""


def _date_commands(
    times: np.ndarray, image_times: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unstamped commands dated by the stamp of the next kept image in the bag's order (see
    :mod:`tpsr_ros.core.resample`); returns the times and which commands have one (those
    after the last image have none)."""
    unstamped = times <= UNDATED
    kept = np.flatnonzero(keep)
    following = np.searchsorted(kept, UNDATED - times[unstamped])  # first kept image after
    known = following < kept.size
    dated = np.ones(times.size, dtype=bool)
    dated[np.flatnonzero(unstamped)[~known]] = False
    out = times.copy()
    out[np.flatnonzero(unstamped)[known]] = image_times[kept[following[known]]]
    return out, dated


def read_bag_streams(
    bags: Sequence[Path | str],
    *,
    image_topic: str,
    action_topic: str,
    components: Sequence[str],
    pose_topic: str | None = None,
    reward_topic: str | None = None,
    require_pose: bool = False,
    pose_frame: str = DEFAULT_POSE_FRAME,
) -> list[BagStreams]:
    """Each bag's timed streams, for :func:`fit_stream_spec` and :func:`read_stream_trajectory`.

    ``components`` are the command fields kept (a spec's codebook uses some of them); the
    pose topic is read when given and present (required with ``require_pose``), the reward
    topic when given and of a reward type (:mod:`tpsr_ros.io.reward_messages`).
    """
    if not bags:
        raise ConfigError("no bag given")
    return [
        _read_streams(
            Path(bag),
            image_topic=image_topic,
            action_topic=action_topic,
            pose_topic=pose_topic,
            reward_topic=reward_topic,
            components=tuple(components),
            require_pose=require_pose,
            pose_frame=pose_frame,
        )
        for bag in bags
    ]


def fast_time(data: bytes, log_time_ns: int) -> int:
    """Header stamp read from the CDR bytes, or the log time where the stamp is zero."""
    stamp = header_stamp_ns(data)
    return stamp if stamp > 0 else int(log_time_ns)


def pose_frame_id(path: Path, pose_topic: str, child_frame: str = DEFAULT_POSE_FRAME) -> str | None:
    """The frame the ground-truth poses of ``pose_topic`` in the bag ``path`` are given in:
    the first message's header frame (a ``TFMessage``: the parent of ``child_frame``), or
    None when the bag has no such message."""
    with BagReader(path) as reader:
        msgtype = reader.topics_with_messages.get(pose_topic)
        if msgtype not in POSE_TYPES:
            return None
        for _, _, data in reader.raw_messages([pose_topic]):
            try:
                msg = deserialize(data, msgtype)
            except MessageError:
                continue
            if msgtype != TF_TYPE:
                return str(msg.header.frame_id)
            for transform in msg.transforms:
                if transform.child_frame_id == child_frame:
                    return str(transform.header.frame_id)
    return None
