"""Large images through io.messages: the one-copy serialiser and the zero-copy reader."""

from __future__ import annotations

import numpy as np
import pytest

from tpsr_ros.core.errors import MessageError
from tpsr_ros.io import messages as m


def _rosbags_cdr(msg: object, msgtype: str) -> bytes:
    return bytes(m.jazzy_typestore().serialize_cdr(msg, msgtype))


@pytest.mark.parametrize(
    ("height", "width", "frame_id"),
    [(1080, 1920, "camera"), (480, 640, ""), (101, 333, "a_frame_id_of_odd_length"), (4, 4, "c")],
)
def test_image_round_trip_is_byte_identical_to_rosbags(height, width, frame_id) -> None:
    rgb = np.random.default_rng(height).integers(0, 256, (height, width, 3), dtype=np.uint8)
    msg = m.image_msg(123_456_789_012, rgb, frame_id=frame_id)
    data = m.serialize(msg, m.IMAGE_TYPE)
    assert isinstance(data, bytes)
    assert data == _rosbags_cdr(msg, m.IMAGE_TYPE)
    back = m.deserialize(data, m.IMAGE_TYPE)
    assert m.stamp_of(back) == 123_456_789_012 and back.header.frame_id == frame_id
    np.testing.assert_array_equal(m.image_to_array(back, shape=None, frame_id=frame_id), rgb)


def test_compressed_image_and_a_non_contiguous_view_take_the_same_path() -> None:
    store = m.jazzy_typestore()
    payload = np.random.default_rng(1).integers(0, 256, 300_000, dtype=np.uint8)
    header = m.header_msg(5, "cam")
    msg = store.types["sensor_msgs/msg/CompressedImage"](
        header=header, format="jpeg", data=payload[::2]  # a strided view
    )
    data = m.serialize(msg, "sensor_msgs/msg/CompressedImage")
    assert data == _rosbags_cdr(msg, "sensor_msgs/msg/CompressedImage")
    back = m.deserialize(data, "sensor_msgs/msg/CompressedImage")
    np.testing.assert_array_equal(back.data, payload[::2])
    assert back.format == "jpeg"


def test_deserialised_pixels_are_a_read_only_view_of_the_bytes() -> None:
    rgb = np.random.default_rng(2).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    data = m.serialize(m.image_msg(1, rgb), m.IMAGE_TYPE)
    back = m.deserialize(data, m.IMAGE_TYPE)
    assert np.shares_memory(back.data, np.frombuffer(data, dtype=np.uint8))
    assert not back.data.flags.writeable


def test_a_truncated_large_image_is_a_message_error() -> None:
    rgb = np.zeros((480, 640, 3), dtype=np.uint8)
    data = m.serialize(m.image_msg(1, rgb), m.IMAGE_TYPE)
    with pytest.raises(MessageError, match="cannot decode sensor_msgs/msg/Image"):
        m.deserialize(data[: len(data) // 2], m.IMAGE_TYPE)
