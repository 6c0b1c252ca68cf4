"""CDR of ``visualization_msgs/msg/MarkerArray`` written straight from numpy arrays.

The filter node publishes a marker array after every step; building one message object per
point and walking them with the generic serialiser costs a few tenths of a millisecond per
step, more than the filter update itself. :func:`marker_array_cdr` writes the same bytes
(little-endian CDR, as :func:`tpsr_ros.io.messages.serialize` gives; a test holds the two
equal) from the markers' arrays in a few microseconds. Only the fields the view uses carry
values; texture, UV coordinates, text and mesh are empty. :class:`MarkerArrayTemplate` writes
a run of arrays that differ only in stamps, positions and the values of points and colours
into the bytes of the first: the same bytes again, without walking the fields.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass, field

import numpy as np

from tpsr_ros.io.messages import split_stamp

__all__ = ["MarkerArrayTemplate", "MarkerData", "marker_array_cdr"]

_ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE


@dataclass(frozen=True)
class MarkerData:
    """The fields of one marker that the view sets (the rest are empty or zero).

    Attributes:
        stamp_ns: header stamp.
        frame_id: header frame.
        ns, marker_id, kind: namespace, id and ``type`` (an ``ADD`` action).
        position: ``(3,)`` pose position (orientation: identity).
        scale: ``(3,)``.
        color: ``(4,)`` r, g, b, a.
        points: ``(N, 3)`` (float64).
        colors: ``(M, 4)`` per-point r, g, b, a (float32 on the wire).

    """

    stamp_ns: int
    frame_id: str
    ns: str
    marker_id: int
    kind: int
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    color: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.float32))


class _Writer:
    """Little-endian CDR with alignment counted from the end of the encapsulation header."""

    def __init__(self) -> None:
        self.parts: list[bytes] = [_ENCAPSULATION]
        self.offset = 0
        self.slots: list[tuple[int, int]] = []
        """Where each marker's stamp, position, points and colours went: ``(start, size)``
        in the message's bytes (encapsulation header included), four per marker."""

    def _slot(self, size: int) -> None:
        """The next ``size`` bytes are a value that changes from message to message."""
        self.slots.append((len(_ENCAPSULATION) + self.offset, size))

    def _put(self, data: bytes) -> None:
        self.parts.append(data)
        self.offset += len(data)

    def align(self, size: int) -> None:
        if pad := -self.offset % size:
            self._put(b"\0" * pad)

    def pack(self, fmt: str, size: int, *values: float | int) -> None:
        """Values of one primitive type (``size`` bytes each), aligned to it."""
        self.align(size)
        self._put(struct.pack("<" + fmt, *values))

    def string(self, text: str) -> None:
        data = text.encode() + b"\0"
        self.pack("I", 4, len(data))
        self._put(data)

    def array(self, values: np.ndarray, dtype: str, size: int) -> None:
        """A sequence of fixed-size structs of one primitive type: count, then the values
        (aligned only when there are any, as every CDR serialiser does)."""
        self.pack("I", 4, values.shape[0])
        data = b""
        if values.shape[0]:
            self.align(size)
            data = np.ascontiguousarray(values, dtype=dtype).tobytes()
        self._slot(len(data))
        self._put(data)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        self.pack("iI", 4, *split_stamp(stamp_ns))
        self.string(frame_id)

    def marker(self, marker: MarkerData) -> None:
        self.align(4)
        self._slot(8)
        self.pack("iI", 4, *split_stamp(marker.stamp_ns))
        # from a 4-aligned offset on, these bytes depend on the names and numbers only
        self._put(_after_stamp(marker.frame_id, marker.ns, marker.marker_id, marker.kind))
        self.align(8)
        self._slot(24)
        self.pack("3d", 8, *marker.position)
        # 8-aligned still: orientation, scale, color, lifetime 0, frame_locked
        self._put(_after_position(marker.scale, marker.color))
        self.array(marker.points, "<f8", 8)
        self.array(marker.colors, "<f4", 4)
        self._put(_TAIL)  # the colours leave a 4-aligned offset; the tail needs no more

    def tail(self) -> None:
        """Texture, UV coordinates, text and mesh, all empty."""
        self.string("")  # texture_resource
        self.header(0, "")  # texture: an empty CompressedImage
        self.string("")
        self.pack("I", 4, 0)
        self.pack("I", 4, 0)  # uv_coordinates
        self.string("")  # text
        self.string("")  # mesh_resource
        self.string("")  # mesh_file: filename, data
        self.pack("I", 4, 0)
        self.pack("?", 1, False)  # mesh_use_embedded_materials


@functools.lru_cache(maxsize=64)
def _after_stamp(frame_id: str, ns: str, marker_id: int, kind: int) -> bytes:
    """The bytes between a marker's stamp and its pose, from a 4-aligned offset."""
    writer = _Writer()
    writer.string(frame_id)
    writer.string(ns)
    writer.pack("iii", 4, marker_id, kind, 0)  # id, type, action ADD
    return b"".join(writer.parts[1:])


@functools.lru_cache(maxsize=64)
def _after_position(
    scale: tuple[float, float, float], color: tuple[float, float, float, float]
) -> bytes:
    """The bytes between a marker's position and its points, from an 8-aligned offset."""
    return struct.pack("<7d4fiI?", 0.0, 0.0, 0.0, 1.0, *scale, *color, 0, 0, False)


def _empty_tail() -> bytes:
    writer = _Writer()
    writer.tail()
    return b"".join(writer.parts[1:])


_TAIL = _empty_tail()


def marker_array_cdr(markers: list[MarkerData]) -> bytes:
    """CDR bytes of a ``visualization_msgs/msg/MarkerArray`` of ``markers``."""
    writer = _Writer()
    writer.pack("I", 4, len(markers))
    for marker in markers:
        writer.marker(marker)
    return b"".join(writer.parts)


class MarkerArrayTemplate:
    """CDR of marker arrays shaped as ``markers`` (the same names, kinds, scales, colours
    and numbers of points and per-point colours): ``markers``' bytes with each marker's
    stamp, position, points and colours written in, byte for byte what
    :func:`marker_array_cdr` gives for the same markers."""

    def __init__(self, markers: list[MarkerData]) -> None:
        writer = _Writer()
        writer.pack("I", 4, len(markers))
        for marker in markers:
            writer.marker(marker)
        self._template = b"".join(writer.parts)
        self._slots = [writer.slots[i : i + 4] for i in range(0, len(writer.slots), 4)]
        self.shape = tuple((len(m.points), len(m.colors)) for m in markers)
        """Points and per-point colours of each marker."""

    def __call__(
        self,
        stamp_ns: int,
        positions: list[np.ndarray | None],
        points: list[np.ndarray | None],
        colors: list[bytes | None],
    ) -> bytes:
        """The array with every marker stamped ``stamp_ns``, marker ``i`` at ``positions[i]``
        (``(3,)`` float64; None: the origin), with ``points[i]`` (``(N_i, 3)`` float64; None:
        none) and ``colors[i]`` (the bytes of ``(M_i, 4)`` little-endian float32; None: none)."""
        out = bytearray(self._template)
        stamp = _STAMP.pack(*split_stamp(stamp_ns))
        for (at_stamp, at_position, at_points, at_colors), position, values, color in zip(
            self._slots, positions, points, colors, strict=True
        ):
            out[at_stamp[0] : at_stamp[0] + 8] = stamp
            if position is not None:
                out[at_position[0] : at_position[0] + 24] = _f8_bytes(position, at_position[1])
            if values is not None:
                out[at_points[0] : at_points[0] + at_points[1]] = _f8_bytes(values, at_points[1])
            if color is not None:
                if len(color) != at_colors[1]:
                    raise ValueError(f"{len(color)} bytes of colours for {at_colors[1]}")
                out[at_colors[0] : at_colors[0] + at_colors[1]] = color
        return bytes(out)


_STAMP = struct.Struct("<iI")


def _f8_bytes(values: np.ndarray, size: int) -> bytes:
    """Little-endian float64 bytes of ``values``, refused unless they are ``size`` bytes."""
    data = np.ascontiguousarray(values, dtype="<f8").tobytes()
    if len(data) != size:
        raise ValueError(f"{len(data)} bytes of values for a slot of {size}")
    return data
