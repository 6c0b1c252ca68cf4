"""Camera messages to pixels and observations: ``Image`` (raw) and ``CompressedImage``.

:func:`decode_image` validates and decodes one message into ``(H, W, C)`` pixels (RGB order
for colour, ``C = 1`` for grey; uint8, or uint16 for ``mono16``/``16UC1``); JPEG and PNG are
decoded with Pillow. :func:`image_observations` then applies the one preprocessing of
:mod:`tpsr_ros.core.images`. Every refusal is a :class:`~tpsr_ros.core.errors.MessageError`
naming the rule broken; callers add the topic and message index.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any

import numpy as np

from tpsr_ros.core.errors import EncodingError, MessageError
from tpsr_ros.core.images import Preprocessing, preprocess_images

__all__ = [
    "COMPRESSED_IMAGE_TYPE",
    "ENCODINGS",
    "IMAGE_TYPE",
    "IMAGE_TYPES",
    "decode_image",
    "image_observations",
    "raw_pixels",
]

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)
ENCODINGS: dict[str, tuple[int, str, tuple[int, ...]]] = {
    # encoding: (channels, dtype, channel order giving RGB or grey)
    "rgb8": (3, "u1", (0, 1, 2)),
    "bgr8": (3, "u1", (2, 1, 0)),
    "rgba8": (4, "u1", (0, 1, 2)),
    "bgra8": (4, "u1", (2, 1, 0)),
    "mono8": (1, "u1", (0,)),
    "8UC1": (1, "u1", (0,)),
    "mono16": (1, "u2", (0,)),
    "16UC1": (1, "u2", (0,)),
}
"""Raw encodings accepted (sensor_msgs/image_encodings.hpp names)."""
MAX_PIXELS = 4096 * 4096
COMPRESSED_FORMATS = ("jpeg", "png")


def _raw(msg: Any) -> np.ndarray:
    return raw_pixels(
        np.asarray(msg.data, dtype=np.uint8), int(msg.height), int(msg.width), int(msg.step),
        str(msg.encoding), bool(msg.is_bigendian),
    )


def raw_pixels(
    data: np.ndarray | memoryview, height: int, width: int, step: int, encoding: str,
    is_bigendian: bool,
) -> np.ndarray:
    """Pixels ``(H, W, C)`` of a raw ``Image``'s fields (``data``: its bytes as uint8)."""
    if encoding not in ENCODINGS:
        raise EncodingError(
            f"image encoding {encoding[:40]!r} is not one of {', '.join(ENCODINGS)}"
        )
    channels, dtype, order = ENCODINGS[encoding]
    if height < 1 or width < 1 or height * width > MAX_PIXELS:
        raise MessageError(f"image size {height}x{width} is empty or larger than {MAX_PIXELS} px")
    item = np.dtype(dtype).itemsize
    row_bytes = width * channels * item
    if step < row_bytes:  # drivers may pad rows (step > row bytes), never shorten them
        raise MessageError(
            f"image step {step} is less than width {width} x {channels * item} bytes "
            f"per {encoding} pixel"
        )
    data = np.frombuffer(memoryview(data), dtype=np.uint8)
    if data.size != height * step:
        raise MessageError(f"image holds {data.size} bytes, expected {height} x {step}")
    if step != row_bytes:
        data = np.ascontiguousarray(data.reshape(height, step)[:, :row_bytes]).ravel()
    endian = ">" if is_bigendian else "<"
    pixels = data.view(np.dtype(dtype).newbyteorder(endian) if item > 1 else dtype)
    pixels = pixels.reshape(height, width, channels)
    if item > 1:
        pixels = pixels.astype(np.uint16)
    return pixels[:, :, list(order)] if order != tuple(range(channels)) else pixels


def _compressed(msg: Any) -> np.ndarray:
    from PIL import Image as PILImage

    fmt = str(msg.format).lower()
    if not any(name in fmt for name in COMPRESSED_FORMATS):
        raise EncodingError(f"compressed format {fmt[:40]!r} is not jpeg or png")
    data = bytes(np.asarray(msg.data, dtype=np.uint8))
    try:
        with PILImage.open(io.BytesIO(data)) as image:
            if image.format not in ("JPEG", "PNG"):
                raise EncodingError(f"compressed data is {image.format}, not JPEG or PNG")
            if image.width * image.height > MAX_PIXELS:
                raise MessageError(f"compressed image of {image.width}x{image.height} is too large")
            grey = image.mode in ("L", "I;16", "I", "1", "LA")
            if image.mode in ("I;16", "I"):
                pixels = np.asarray(image, dtype=np.uint16)
            else:
                pixels = np.asarray(image.convert("L" if grey else "RGB"), dtype=np.uint8)
    except MessageError:
        raise
    except Exception as exc:  # Pillow raises OSError, SyntaxError, ValueError... on garbage
        raise MessageError(f"corrupt {fmt.split(';')[0] or 'compressed'} image: {exc}") from None
    return pixels[:, :, None] if pixels.ndim == 2 else pixels


def decode_image(msg: Any, msgtype: str) -> np.ndarray:
    """Pixels ``(H, W, C)`` of an ``Image`` or ``CompressedImage`` message (see module docs)."""
    if msgtype == IMAGE_TYPE:
        return _raw(msg)
    if msgtype == COMPRESSED_IMAGE_TYPE:
        return _compressed(msg)
    raise MessageError(f"camera type {msgtype} is not one of {', '.join(IMAGE_TYPES)}")


def image_observations(
    images: Sequence[np.ndarray], preprocessing: Preprocessing
) -> np.ndarray:
    """Observations ``(T, k)`` of decoded images, batched by image shape and dtype."""
    if not images:
        return np.zeros((0, preprocessing.size))
    out = np.empty((len(images), preprocessing.size))
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, image in enumerate(images):
        groups.setdefault((image.shape, image.dtype.str), []).append(i)
    for rows in groups.values():
        out[rows] = preprocess_images(np.stack([images[i] for i in rows]), preprocessing)
    return out
