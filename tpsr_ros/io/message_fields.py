"""Fields of decoded ROS messages, read without a typestore.

Decoded messages (rosbags' classes or rclpy's, alike) are read by attribute; nothing here
deserialises or builds a message, so the ROS-free parts of the nodes (e.g.
:mod:`tpsr_ros.filter_node.inputs`) read them without rosbags. Every refusal is a
:class:`~tpsr_ros.core.errors.MessageError` naming the rule broken.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tpsr_ros.core.errors import MessageError
from tpsr_ros.core.units import NS_PER_S as _NS

__all__ = [
    "image_to_array",
    "pose_to_planar",
    "pose_to_xy",
    "quaternion_heading",
    "stamp_of",
    "twist_components",
    "twist_to_xy",
    "yaw_cos_sin",
]


def stamp_of(msg: Any) -> int:
    """Stamp of a message with a ``header`` (or a Clock) in integer nanoseconds."""
    stamp = msg.clock if hasattr(msg, "clock") else msg.header.stamp
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def image_to_array(
    msg: Any, shape: tuple[int, int] | None = (16, 16), frame_id: str | None = None
) -> np.ndarray:
    """Validate an rgb8 image message and return it as an ``(H, W, 3)`` uint8 array.

    ``shape`` and ``frame_id``, when given, must match; anything else raises
    ``MessageError`` naming the mismatch.
    """
    if msg.encoding != "rgb8":
        raise MessageError(f"image encoding {msg.encoding!r} is not rgb8")
    height, width = int(msg.height), int(msg.width)
    if shape is not None and (height, width) != tuple(shape):
        raise MessageError(f"image is {height}x{width}, expected {shape[0]}x{shape[1]}")
    if int(msg.step) != 3 * width:
        raise MessageError(f"image step {msg.step} does not match width {width} x 3 bytes")
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size != height * width * 3:
        raise MessageError(f"image holds {data.size} bytes, expected {height * width * 3}")
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise MessageError(f"image frame {msg.header.frame_id!r} is not {frame_id!r}")
    return data.reshape(height, width, 3)


def twist_to_xy(msg: Any) -> tuple[float, float]:
    """Planar linear velocity of a Twist or TwistStamped; non-finite values are refused."""
    twist = msg.twist if hasattr(msg, "twist") else msg
    vx, vy = float(twist.linear.x), float(twist.linear.y)
    if not (np.isfinite(vx) and np.isfinite(vy)):
        raise MessageError(f"velocity ({vx}, {vy}) is not finite")
    return vx, vy


def twist_components(msg: Any, components: tuple[str, ...]) -> np.ndarray:
    """Chosen components (``"linear.x"``, ``"angular.z"``...) of a Twist or TwistStamped."""
    twist = msg.twist if hasattr(msg, "twist") else msg
    values = np.empty(len(components))
    for i, name in enumerate(components):
        part, axis = name.split(".")
        values[i] = float(getattr(getattr(twist, part), axis))
    if not np.isfinite(values).all():
        shown = dict(zip(components, values.tolist(), strict=True))
        raise MessageError(f"command {shown} is not finite")
    return values


def pose_to_xy(msg: Any) -> tuple[float, float]:
    """Planar position of a PoseStamped."""
    return float(msg.pose.position.x), float(msg.pose.position.y)


def yaw_cos_sin(x: float, y: float, z: float, w: float) -> tuple[float, float]:
    """``(cos, sin)`` of the yaw (heading about z) of the quaternion ``(x, y, z, w)``.

    Computed from the unnormalised rotation matrix entries, so a quaternion of any length
    gives its angle; a zero or non-finite one counts as no rotation.
    """
    cos_part = w * w + x * x - y * y - z * z
    sin_part = 2.0 * (w * z + x * y)
    norm = float(np.hypot(cos_part, sin_part))
    if not (norm > 0 and np.isfinite(norm)):
        return 1.0, 0.0
    return cos_part / norm, sin_part / norm


def quaternion_heading(q: Any) -> tuple[float, float]:
    """:func:`yaw_cos_sin` of a ``geometry_msgs/msg/Quaternion``."""
    return yaw_cos_sin(float(q.x), float(q.y), float(q.z), float(q.w))


def pose_to_planar(msg: Any) -> tuple[float, float, float, float]:
    """``(x, y, cos heading, sin heading)`` of a PoseStamped; non-finite positions refused."""
    x, y = pose_to_xy(msg)
    if not (np.isfinite(x) and np.isfinite(y)):
        raise MessageError(f"value ({x}, {y}) is not finite")
    return (x, y, *quaternion_heading(msg.pose.orientation))
