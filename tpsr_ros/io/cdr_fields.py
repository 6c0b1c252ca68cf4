"""The few fields a trajectory needs, read straight from CDR bytes: no message objects.

Reading a bag used to spend most of its time building a rosbags object per message, only
to take a stamp and a handful of numbers (or an image's pixels) out of it. The messages of
one topic differ from each other only in those fields, at the same places: so a decoder
here learns a message's *layout* once and reads every later message of that layout at
fixed offsets with ``struct`` (images: a view of the pixel bytes, copied once per chunk).

Learning a layout is the safe, slow path: the message is deserialised by rosbags (every
CDR rule: encapsulation, lengths, string terminators, UTF-8, sizes) and checked by the same
functions as any decoded message (:func:`~tpsr_ros.io.messages.image_to_array`,
:func:`~tpsr_ros.io.images.decode_image`, :func:`~tpsr_ros.io.messages.twist_components`,
:func:`~tpsr_ros.io.messages.reward_to_sample`);
a short CDR walk then finds the value offsets (alignment counted from after the 4-byte
encapsulation header, either byte order), and the values read there must equal rosbags'.
A layout is the message length plus every byte outside the stamp and the value block
(the block holds the values read, and for a twist or pose also the components not read);
a later message is read the fast way only if its length and all those bytes are equal,
i.e. it is the learnt message with another stamp and other values, which rosbags would
parse the same way. Anything else (another frame_id, encoding, size, padding, byte order,
hostile bytes) is learnt afresh: deserialised and checked again, so a bad one is refused
with the same ``MessageError`` as before and an image is never read at a wrong offset.
Values read the fast way are still checked per message (a valid stamp; finite
velocities, poses and rewards).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tpsr_ros.core.errors import MessageError
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.io.images import decode_image, raw_pixels
from tpsr_ros.io.message_fields import yaw_cos_sin
from tpsr_ros.io.messages import (
    ACTION_TYPE,
    IMAGE_TYPE,
    POSE_TYPE,
    REWARD_TYPE,
    deserialize,
    image_to_array,
    pose_to_planar,
    pose_to_xy,
    reward_to_sample,
    stamp_of,
)

__all__ = [
    "ImageDecoder",
    "PoseDecoder",
    "RawImageDecoder",
    "RewardDecoder",
    "TwistDecoder",
]

_ENCAPSULATION = 4  # bytes before the CDR stream; alignment counts from here
_STAMP_END = 12  # int32 sec, uint32 nanosec of std_msgs/Header right after the encapsulation


class _Walk:
    """Offsets in CDR bytes already validated by rosbags (no checks of its own)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.order = "<" if data[1] else ">"
        self.pos = _STAMP_END  # past the encapsulation and the header's stamp

    def align(self, size: int) -> None:
        self.pos = _ENCAPSULATION + (-(-(self.pos - _ENCAPSULATION) // size) * size)

    def uint32(self) -> int:
        self.align(4)
        (value,) = struct.unpack_from(self.order + "I", self.data, self.pos)
        self.pos += 4
        return int(value)

    def string(self) -> None:
        length = self.uint32()  # (``self.pos += self.uint32()`` would drop the 4 bytes)
        self.pos += length

    def text(self) -> str:
        length = self.uint32()
        start, self.pos = self.pos, self.pos + length
        return bytes(self.data[start : start + length - 1]).decode()  # without the NUL

    def skip(self, size: int) -> None:
        self.pos += size


@dataclass(frozen=True)
class _Layout:
    """Where a learnt message keeps its values; the bytes that must match to reuse it.

    ``head``, ``prefix`` and ``suffix`` are the learnt message's bytes before the stamp,
    between the stamp and the values, and after the values; ``unpack`` reads the stamp's
    ``sec`` and ``nanosec`` and the values (``value_format``) in one call.
    """

    size: int
    head: bytes
    prefix: bytes
    suffix: bytes
    values: int  # offset of the first value read
    values_end: int  # and the end of the values
    unpack: Callable[[bytes], tuple[Any, ...]]
    info: tuple[Any, ...] = ()  # what else a decoder needs to know of the layout

    @classmethod
    def of(
        cls, data: bytes, values: int, values_end: int, value_format: str,
        info: tuple[Any, ...] = (),
    ) -> _Layout:
        order = "<" if data[1] else ">"
        fields = struct.Struct(f"{order}{_ENCAPSULATION}xiI{values - _STAMP_END}x{value_format}")
        return cls(
            size=len(data),
            head=bytes(data[:_ENCAPSULATION]),
            prefix=bytes(data[_STAMP_END:values]),
            suffix=bytes(data[values_end:]),
            values=values,
            values_end=values_end,
            unpack=fields.unpack_from,
            info=info,
        )


class _Decoder:
    """Stamp and values of one message type; subclasses say where the values are."""

    msgtype = ""

    def __init__(self) -> None:
        self._layout: _Layout | None = None

    def decode(self, data: bytes) -> tuple[int, Any]:
        """``(stamp_ns, value)`` of the CDR bytes ``data``; bad bytes raise ``MessageError``."""
        return self._read(data, self._known(data) or self._learn(data))

    def decode_known(self, data: bytes) -> tuple[int, Any] | None:
        """:meth:`decode` of a message of the learnt layout with a valid stamp and values;
        None for any other, which the caller reads its own way (and may then :meth:`decode`
        to learn its layout)."""
        layout = self._known(data)
        if layout is None:
            return None
        try:
            return self._read(data, layout)
        except MessageError:
            return None

    def _known(self, data: bytes) -> _Layout | None:
        """The learnt layout if ``data`` has it, else None."""
        layout = self._layout
        if (
            layout is None
            or len(data) != layout.size
            or data[_STAMP_END : layout.values] != layout.prefix
            or data[:_ENCAPSULATION] != layout.head
            or data[layout.values_end :] != layout.suffix
        ):
            return None
        return layout

    def _read(self, data: bytes, layout: _Layout) -> tuple[int, Any]:
        fields = layout.unpack(data)
        if fields[0] < 0 or fields[1] >= NS_PER_S:
            raise MessageError(f"header stamp {fields[0]} s {fields[1]} ns is not a valid time")
        return fields[0] * NS_PER_S + fields[1], self._value(data, layout, fields)

    def _learn(self, data: bytes) -> _Layout:
        msg = deserialize(data, self.msgtype)  # every CDR rule, as rosbags applies it
        expected = self._check(msg)
        layout = self._locate(_Walk(data))
        fields = layout.unpack(data)
        stamp = fields[0] * NS_PER_S + fields[1]
        if stamp != stamp_of(msg) or not _same(self._value(data, layout, fields), expected):
            raise MessageError(  # a decoder bug, never expected: refuse rather than guess
                f"cannot decode {self.msgtype}: the fields found in its bytes disagree with "
                "rosbags' deserialisation"
            )
        self._layout = layout
        return layout

    def _check(self, msg: Any) -> Any:
        """Validate a deserialised message; return the value :meth:`_value` must give."""
        raise NotImplementedError

    def _locate(self, walk: _Walk) -> _Layout:
        """The layout of the (valid) message being walked."""
        raise NotImplementedError

    def _value(self, data: bytes, layout: _Layout, fields: tuple[Any, ...]) -> Any:
        """The value of a message of ``layout``; ``fields`` = ``(sec, nanosec, *values)``."""
        raise NotImplementedError


def _same(read: Any, expected: Any) -> bool:
    if isinstance(read, np.ndarray):
        return read.dtype == expected.dtype and bool(np.array_equal(read, expected))
    if isinstance(read, memoryview):
        return bytes(read) == np.asarray(expected, dtype=np.uint8).tobytes()
    return bool(np.array_equal(np.asarray(read), np.asarray(expected), equal_nan=True))


def _finite_pair(x: float, y: float, what: str) -> tuple[float, float]:
    if not (math.isfinite(x) and math.isfinite(y)):
        raise MessageError(f"{what} ({x}, {y}) is not finite")
    return x, y


class RawImageDecoder(_Decoder):
    """A raw ``sensor_msgs/msg/Image`` of any encoding of :data:`~tpsr_ros.io.images.ENCODINGS`
    and any size: pixels ``(H, W, C)`` as :func:`~tpsr_ros.io.images.decode_image` gives them.
    """

    msgtype = IMAGE_TYPE

    def _check(self, msg: Any) -> Any:
        return decode_image(msg, IMAGE_TYPE)

    def _locate(self, walk: _Walk) -> _Layout:
        walk.string()  # header.frame_id
        height, width = walk.uint32(), walk.uint32()
        encoding = walk.text()
        is_bigendian = bool(walk.data[walk.pos])
        walk.skip(1)
        step = walk.uint32()
        size = walk.uint32()  # data: a uint8 sequence, checked by _check
        info = (height, width, step, encoding, is_bigendian)
        return _Layout.of(walk.data, walk.pos, walk.pos + size, "", info)

    def _value(self, data: bytes, layout: _Layout, fields: tuple[Any, ...]) -> np.ndarray:
        return raw_pixels(memoryview(data)[layout.values : layout.values_end], *layout.info)


class ImageDecoder(RawImageDecoder):
    """rgb8 ``sensor_msgs/msg/Image`` (the simulator's camera): the pixel bytes (row-major
    ``H x W x 3``) as a view, copied once per chunk.

    ``shape`` ``(H, W)`` is required of every image; ``None`` takes the first image's and
    then requires it of the rest (:attr:`shape`).
    """

    def __init__(self, shape: tuple[int, int] | None) -> None:
        super().__init__()
        self.shape = None if shape is None else (int(shape[0]), int(shape[1]))

    def _check(self, msg: Any) -> Any:
        pixels = image_to_array(msg, shape=self.shape)
        self.shape = self.shape or (int(pixels.shape[0]), int(pixels.shape[1]))
        return pixels

    def _value(self, data: bytes, layout: _Layout, fields: tuple[Any, ...]) -> memoryview:
        return memoryview(data)[layout.values : layout.values_end]


_TWIST_FIELDS = ("linear.x", "linear.y", "linear.z", "angular.x", "angular.y", "angular.z")


class TwistDecoder(_Decoder):
    """``geometry_msgs/msg/TwistStamped``: two of its components, by default the planar
    velocity ``(linear.x, linear.y)`` (``drive``: ``(linear.x, angular.z)``); finite."""

    msgtype = ACTION_TYPE

    def __init__(self, components: tuple[str, str] = ("linear.x", "linear.y")) -> None:
        super().__init__()
        self.components = tuple(components)
        self._columns = [_TWIST_FIELDS.index(c) for c in self.components]

    def _check(self, msg: Any) -> Any:
        first, second = (
            float(getattr(getattr(msg.twist, part), axis))
            for part, axis in (name.split(".") for name in self.components)
        )
        return _finite_pair(first, second, "velocity")

    def _locate(self, walk: _Walk) -> _Layout:
        walk.string()  # header.frame_id
        walk.align(8)  # twist.linear.x
        return _Layout.of(walk.data, walk.pos, walk.pos + 6 * 8, "6d")

    def _value(self, data: bytes, layout: _Layout, fields: tuple[Any, ...]) -> tuple[float, float]:
        first, second = (fields[2 + c] for c in self._columns)
        return _finite_pair(first, second, "velocity")


class PoseDecoder(_Decoder):
    """``geometry_msgs/msg/PoseStamped``: the planar position ``(x, y)``, finite; with
    ``heading``, also the cosine and sine of its yaw (:func:`pose_to_planar`)."""

    msgtype = POSE_TYPE

    def __init__(self, heading: bool = False) -> None:
        super().__init__()
        self.heading = heading

    def _check(self, msg: Any) -> Any:
        return pose_to_planar(msg) if self.heading else pose_to_xy(msg)

    def _locate(self, walk: _Walk) -> _Layout:
        walk.string()  # header.frame_id
        walk.align(8)  # pose.position.x
        return _Layout.of(walk.data, walk.pos, walk.pos + 7 * 8, "7d")

    def _value(self, data: bytes, layout: _Layout, fields: tuple[Any, ...]) -> tuple[float, ...]:
        x, y = _finite_pair(fields[2], fields[3], "value")
        return (x, y, *yaw_cos_sin(*fields[5:9])) if self.heading else (x, y)


class RewardDecoder(_Decoder):
    """The simulator's reward ``sensor_msgs/msg/JointState`` (:func:`reward_msg`): the reward.

    The names must be :data:`~tpsr_ros.io.messages.REWARD_NAMES`; the reward finite.
    """

    msgtype = REWARD_TYPE

    def _check(self, msg: Any) -> Any:
        return reward_to_sample(msg).reward

    def _locate(self, walk: _Walk) -> _Layout:
        walk.string()  # header.frame_id
        for _ in range(walk.uint32()):  # name: sequence<string>
            walk.string()
        walk.uint32()  # position: sequence<float64> of 3 (checked by reward_to_sample)
        walk.align(8)
        return _Layout.of(walk.data, walk.pos, walk.pos + 3 * 8, "d")

    def _value(self, data: bytes, layout: _Layout, fields: tuple[Any, ...]) -> float:
        reward = fields[2]
        if not math.isfinite(reward):
            raise MessageError(f"value {reward} is not finite")
        return float(reward)
