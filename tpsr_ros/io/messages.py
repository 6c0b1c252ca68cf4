"""ROS 2 message construction, validation and CDR (de)serialisation.

One source for every message layout: the ``rosbags`` ROS 2 Jazzy typestore. The bag
writer, the learner and every transport build and read messages through these
functions, so a field is spelled in one place. Stamps are integer nanoseconds.

Message choices (see msgs_doc/topics.md):
- reward: ``sensor_msgs/msg/JointState``, the stock stamped, self-describing float vector
  (names ``reward``, ``wall_contact``, ``goal_zone``);
- predictive state: ``sensor_msgs/msg/JointState`` too (names ``b0``..``b{r-1}``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from functools import cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from tpsr_ros.core.errors import MessageError
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io.message_fields import (
    image_to_array,
    pose_to_planar,
    pose_to_xy,
    quaternion_heading,
    stamp_of,
    twist_components,
    twist_to_xy,
)

__all__ = [
    "ACTION_TYPE",
    "CLOCK_TYPE",
    "IMAGE_TYPE",
    "POSE_TYPE",
    "REWARD_NAMES",
    "REWARD_TYPE",
    "STATE_TYPE",
    "TWIST_TYPE",
    "RewardSample",
    "StampedTemplate",
    "StateEncoder",
    "clock_msg",
    "deserialize",
    "header_stamp_ns",
    "heading_quaternion",
    "image_msg",
    "image_problem",
    "image_to_array",
    "jazzy_typestore",
    "message_definition",
    "peek_stamp",
    "pose_msg",
    "pose_to_planar",
    "pose_to_xy",
    "quaternion_heading",
    "reward_msg",
    "reward_to_sample",
    "serialize",
    "split_stamp",
    "stamp_of",
    "stamped_twist",
    "starts_with_header",
    "state_msg",
    "state_to_array",
    "twist_components",
    "twist_from_components",
    "twist_msg",
    "twist_stamped_msg",
    "twist_to_xy",
]

IMAGE_TYPE = "sensor_msgs/msg/Image"
ACTION_TYPE = "geometry_msgs/msg/TwistStamped"
TWIST_TYPE = "geometry_msgs/msg/Twist"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
REWARD_TYPE = "sensor_msgs/msg/JointState"
STATE_TYPE = "sensor_msgs/msg/JointState"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
HEADER_TYPE = "std_msgs/msg/Header"

REWARD_NAMES = ("reward", "wall_contact", "goal_zone")


@cache
def jazzy_typestore() -> Typestore:
    """Return the ROS 2 Jazzy typestore (built once; it is immutable in use)."""
    return get_typestore(Stores.ROS2_JAZZY)


def _t(name: str) -> Any:
    return jazzy_typestore().types[name]


def message_definition(msgtype: str) -> str:
    """Return the full ``ros2msg`` definition of ``msgtype``, its dependencies appended.

    The schema text rosbag2 stores in MCAP files and Foxglove reads to decode CDR, from
    the Jazzy typestore; an unknown type raises ``MessageError``.
    """
    try:
        text, _ = jazzy_typestore().generate_msgdef(msgtype, ros_version=2)
    except Exception as exc:  # rosbags raises its own types for unknown messages
        raise MessageError(f"unknown message type {msgtype!r} ({exc})") from None
    return str(text)


def split_stamp(stamp_ns: int) -> tuple[int, int]:
    """Split integer nanoseconds into ROS ``(sec, nanosec)``; negative stamps are refused."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise MessageError(f"negative stamp {stamp_ns} ns cannot be a ROS time")
    return stamp_ns // _NS, stamp_ns % _NS


def _header(stamp_ns: int, frame_id: str) -> Any:
    sec, nanosec = split_stamp(stamp_ns)
    return _t("std_msgs/msg/Header")(
        stamp=_t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def starts_with_header(msgtype: str) -> bool:
    """Whether messages of ``msgtype`` start with a ``std_msgs/Header`` (a stamp to read)."""
    defs = jazzy_typestore().fielddefs.get(msgtype)
    if not defs or not defs[1]:
        return False
    _, node = defs[1][0]
    return bool(node[0].name == "NAME" and node[1] == "std_msgs/msg/Header")


def header_stamp_ns(data: bytes | memoryview) -> int:
    """Stamp of serialised CDR bytes of a message that starts with a ``std_msgs/Header``.

    Reads only the encapsulation header and the stamp (``int32 sec``, ``uint32 nanosec``),
    so a reader can place large messages (images) in time without deserialising them.
    """
    raw = bytes(data[:12])
    if len(raw) < 12 or raw[0] != 0 or raw[1] not in (0, 1):
        raise MessageError("the CDR data is too short or not plain CDR")
    order = "<" if raw[1] == 1 else ">"
    sec, nanosec = struct.unpack(order + "iI", raw[4:12])
    if sec < 0 or nanosec >= _NS:
        raise MessageError(f"header stamp {sec} s {nanosec} ns is not a valid time")
    return sec * _NS + nanosec


def peek_stamp(data: bytes | memoryview) -> int | None:
    """:func:`header_stamp_ns`, or None where the bytes hold no readable stamp (for
    error messages and for counting, where an unreadable message is handled elsewhere)."""
    try:
        return header_stamp_ns(data)
    except MessageError:
        return None


# Below this many bytes of trailing byte data the generic path is as fast.
_SPLICE_MIN_BYTES = 1 << 16
_EMPTY_BYTES = np.zeros(0, dtype=np.uint8)


@cache
def _trailing_byte_field(msgtype: str) -> str | None:
    """Name of ``msgtype``'s last field when it is an unbounded uint8/byte sequence.

    Such a field (``Image.data``, ``CompressedImage.data``) ends the CDR stream and needs
    no alignment, so its bytes can be appended to the serialised rest unchanged.
    """
    fields = jazzy_typestore().fielddefs.get(msgtype, (None, []))[1]
    if not fields:
        return None
    name, (kind, spec) = fields[-1]
    if kind.name != "SEQUENCE" or spec[1]:
        return None
    sub_kind, sub_spec = spec[0]
    if sub_kind.name == "BASE" and sub_spec[0] in ("uint8", "byte", "char"):
        return str(name)
    return None


def _spliced(msg: Any, msgtype: str, field: str) -> bytes | None:
    """CDR of ``msg`` built with one copy of its large trailing byte field, else None."""
    payload = getattr(msg, field)
    if not isinstance(payload, np.ndarray) or payload.dtype != np.uint8 or payload.ndim != 1:
        return None
    if payload.size < _SPLICE_MIN_BYTES:
        return None
    head = jazzy_typestore().serialize_cdr(replace(msg, **{field: _EMPTY_BYTES}), msgtype)
    # the head ends with the sequence's 4-byte length (0), which is rewritten here
    length = struct.pack("<I" if head[1] == 1 else ">I", payload.size)
    return b"".join((head[:-4], length, np.ascontiguousarray(payload).data))


def serialize(msg: Any, msgtype: str) -> bytes:
    """Serialise to ROS 2 CDR (little endian, with the 4-byte encapsulation header).

    A message ending in a large byte array (an image) is built with one copy of the
    array into the result; everything else goes through the rosbags serialiser.
    """
    field = _trailing_byte_field(msgtype)
    if field is not None:
        spliced = _spliced(msg, msgtype, field)
        if spliced is not None:
            return spliced
    return bytes(jazzy_typestore().serialize_cdr(msg, msgtype))


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    """Deserialise ROS 2 CDR bytes; malformed bytes raise ``MessageError``.

    Arrays in the result are read-only numpy views of ``data`` (no copy of an image's
    pixels): ``bytes`` are immutable, so the views cannot change under the message.
    """
    if isinstance(data, bytes):
        data = memoryview(data)  # rosbags slices a memoryview without copying
    try:
        return jazzy_typestore().deserialize_cdr(data, msgtype)
    except Exception as exc:  # rosbags raises assorted low-level errors on garbage
        raise MessageError(f"cannot decode {msgtype}: {exc}") from None


def image_msg(stamp_ns: int, rgb: np.ndarray, frame_id: str = "camera") -> Any:
    """Build an rgb8 ``sensor_msgs/msg/Image`` from an ``(H, W, 3)`` uint8 array."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise MessageError(f"image must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    height, width, _ = rgb.shape
    return _t(IMAGE_TYPE)(
        header=_header(stamp_ns, frame_id),
        height=height,
        width=width,
        encoding="rgb8",
        is_bigendian=0,
        step=3 * width,
        data=np.ascontiguousarray(rgb).reshape(-1),
    )


# bytes per pixel of the sensor_msgs/image_encodings a camera driver publishes
_BYTES_PER_PIXEL = {
    "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2,
    "rgb16": 6, "bgr16": 6, "rgba16": 8, "bgra16": 8, "8UC1": 1, "8UC3": 3, "8UC4": 4,
    "16UC1": 2, "32FC1": 4, "bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1,
    "bayer_grbg8": 1, "yuv422": 2, "uyvy": 2, "yuyv": 2,
}  # fmt: skip


def image_problem(msg: Any) -> str | None:
    """Why an ``Image`` message cannot be a whole image (None when it can).

    Rows must hold their pixels (``step`` >= ``width`` x bytes per pixel of a known
    encoding; drivers may pad rows, so a larger step is fine) and ``data`` must hold
    exactly ``step`` x ``height`` bytes (fewer: truncated).
    """
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    size = len(msg.data)
    per_pixel = _BYTES_PER_PIXEL.get(str(msg.encoding))
    if per_pixel is not None and step < width * per_pixel:
        return (
            f"step {step} is less than width {width} x {per_pixel} bytes of {msg.encoding}"
        )
    if size != step * height:
        return f"data holds {size} bytes, not step {step} x height {height} = {step * height}"
    return None


def _vector3(x: float, y: float, z: float = 0.0) -> Any:
    return _t("geometry_msgs/msg/Vector3")(x=float(x), y=float(y), z=float(z))


def twist_msg(vx: float, vy: float) -> Any:
    """Planar velocity command as ``geometry_msgs/msg/Twist`` (m/s)."""
    return _t(TWIST_TYPE)(linear=_vector3(vx, vy), angular=_vector3(0.0, 0.0))


def twist_stamped_msg(stamp_ns: int, vx: float, vy: float, frame_id: str = "base_link") -> Any:
    """Executed action as ``geometry_msgs/msg/TwistStamped`` (m/s, commanded, pre-noise)."""
    return stamped_twist(stamp_ns, twist_msg(vx, vy), frame_id)


def stamped_twist(stamp_ns: int, twist: Any, frame_id: str = "base_link") -> Any:
    """``twist`` (a ``geometry_msgs/msg/Twist``) as ``geometry_msgs/msg/TwistStamped``."""
    return _t(ACTION_TYPE)(header=_header(stamp_ns, frame_id), twist=twist)


def twist_from_components(values: dict[str, float]) -> Any:
    """``geometry_msgs/msg/Twist`` with the given components (``"linear.x"``...), others 0."""
    parts: dict[str, dict[str, float]] = {"linear": {}, "angular": {}}
    for name, value in values.items():
        part, axis = name.split(".")
        parts[part][axis] = float(value)
    return _t(TWIST_TYPE)(
        linear=_vector3(**{a: parts["linear"].get(a, 0.0) for a in "xyz"}),
        angular=_vector3(**{a: parts["angular"].get(a, 0.0) for a in "xyz"}),
    )


def heading_quaternion(heading: float | None) -> tuple[float, float]:
    """``(z, w)`` of the rotation by ``heading`` rad about z (None: the identity)."""
    half = 0.0 if heading is None else 0.5 * float(heading)
    return float(np.sin(half)), float(np.cos(half))


def pose_msg(
    stamp_ns: int, x: float, y: float, frame_id: str = "map", heading: float | None = None
) -> Any:
    """Ground-truth planar position as ``geometry_msgs/msg/PoseStamped``: the identity
    orientation (the planar robot's heading never changes), or ``heading`` (rad about z)."""
    z, w = heading_quaternion(heading)
    pose = _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0),
        orientation=_t("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=z, w=w),
    )
    return _t(POSE_TYPE)(header=_header(stamp_ns, frame_id), pose=pose)


@dataclass(frozen=True)
class RewardSample:
    """One step's reward and its two causes."""

    reward: float
    wall_contact: bool
    goal_zone: bool


def _named_vector(stamp_ns: int, names: list[str], values: np.ndarray, frame_id: str) -> Any:
    empty = np.zeros(0, dtype=np.float64)
    return _t(REWARD_TYPE)(
        header=_header(stamp_ns, frame_id),
        name=names,
        position=np.asarray(values, dtype=np.float64),
        velocity=empty,
        effort=empty,
    )


def reward_msg(stamp_ns: int, sample: RewardSample, frame_id: str = "map") -> Any:
    """Reward of a step as a stamped, named ``sensor_msgs/msg/JointState``."""
    values = np.array([sample.reward, float(sample.wall_contact), float(sample.goal_zone)])
    return _named_vector(stamp_ns, list(REWARD_NAMES), values, frame_id)


def reward_to_sample(msg: Any) -> RewardSample:
    """Inverse of :func:`reward_msg`; a message with other names raises ``MessageError``."""
    if tuple(msg.name) != REWARD_NAMES or len(msg.position) != len(REWARD_NAMES):
        raise MessageError(f"reward message names {list(msg.name)} are not {list(REWARD_NAMES)}")
    reward, contact, goal = (float(v) for v in msg.position)
    return RewardSample(reward=reward, wall_contact=contact > 0.5, goal_zone=goal > 0.5)


@cache
def _state_names(size: int) -> tuple[str, ...]:
    """``b0``..``b{size-1}``, made once per state size (a filter publishes one per step)."""
    return tuple(f"b{i}" for i in range(size))


def state_msg(stamp_ns: int, state: np.ndarray, frame_id: str = "tpsr") -> Any:
    """Predictive state b_k as a stamped JointState with names ``b0``..``b{r-1}``."""
    state = np.asarray(state, dtype=np.float64).reshape(-1)
    return _named_vector(stamp_ns, list(_state_names(state.size)), state, frame_id)


class StampedTemplate:
    """CDR of one stamped message type (a ``std_msgs/Header`` first) of which only the stamp
    and a block of ``size`` bytes ending ``suffix`` bytes before the end change: a template's
    bytes with those written in, byte for byte what :func:`serialize` gives for a layout
    the user has checked (every encoder here checks a probe message when it is built)."""

    def __init__(self, template: bytes, size: int, suffix: int = 0) -> None:
        end = len(template) - suffix
        self.size = int(size)
        self.order = "<" if template[1] == 1 else ">"
        self._head, self._tail = template[:4], template[end:]
        self._middle = template[12 : end - size]
        self._stamp = struct.Struct(self.order + "iI").pack

    def __call__(self, stamp_ns: int, block: bytes) -> bytes:
        """The message stamped ``stamp_ns`` holding ``block``."""
        if len(block) != self.size:
            raise MessageError(f"{len(block)} bytes for a block of {self.size}")
        stamp = self._stamp(*split_stamp(stamp_ns))
        return b"".join((self._head, stamp, self._middle, block, self._tail))


class StateEncoder:
    """CDR of :func:`state_msg` messages of one state size and frame, byte for byte what
    :func:`serialize` gives, without building a message: the stamp and the values written
    into the bytes of a template (the names and the empty sequences never change).
    """

    def __init__(self, size: int, frame_id: str = "tpsr") -> None:
        self.size = int(size)
        template = serialize(state_msg(0, np.zeros(self.size), frame_id), STATE_TYPE)
        # position's float64 values end the message but for the counts of the empty
        # velocity and effort sequences (a uint32 each)
        self._template = StampedTemplate(template, 8 * self.size, suffix=8)
        self._dtype = np.dtype(self._template.order + "f8")
        stamp, probe = 1_500_000_002, np.arange(1.0, self.size + 1.0)
        if self(stamp, probe) != serialize(state_msg(stamp, probe, frame_id), STATE_TYPE):
            raise MessageError("the state message layout is not the one StateEncoder writes")

    def __call__(self, stamp_ns: int, state: np.ndarray) -> bytes:
        """CDR bytes of ``state_msg(stamp_ns, state)``."""
        values = np.asarray(state, dtype=self._dtype).reshape(-1)
        if values.size != self.size:
            raise MessageError(f"a state of {values.size} values is not one of {self.size}")
        return self._template(stamp_ns, values.tobytes())


def state_to_array(msg: Any) -> np.ndarray:
    """Predictive state carried by a :func:`state_msg` message."""
    return np.asarray(msg.position, dtype=np.float64).copy()


def header_msg(stamp_ns: int, frame_id: str) -> Any:
    """Build a bare ``std_msgs/msg/Header``: a stamped event whose ``frame_id`` names it."""
    return _header(stamp_ns, frame_id)


def clock_msg(stamp_ns: int) -> Any:
    """Simulation time as ``rosgraph_msgs/msg/Clock``."""
    sec, nanosec = split_stamp(stamp_ns)
    return _t(CLOCK_TYPE)(clock=_t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec))
