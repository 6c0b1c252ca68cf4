"""The CDR field decoders against rosbags' deserialisation: every layout, byte order, mutation."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from test_fuzz import mutate
from test_robot_inputs import raw_msg

from tpsr_ros.core.errors import MessageError
from tpsr_ros.io import messages as m
from tpsr_ros.io.cdr_fields import (
    ImageDecoder,
    PoseDecoder,
    RawImageDecoder,
    RewardDecoder,
    TwistDecoder,
)
from tpsr_ros.io.images import decode_image
from tpsr_ros.io.messages import peek_stamp

S = 1_000_000_000
FRAMES = ["", "a", "ab", "abc", "abcd", "abcde", "abcdef", "abcdefg", "camera", "é"]
"""frame_id lengths 0..7 and more: the values after the header move through every alignment."""


def _cdr(msg: Any, msgtype: str, little: bool) -> bytes:
    return bytes(m.jazzy_typestore().serialize_cdr(msg, msgtype, little_endian=little))


def _finite(value: tuple[float, ...] | float) -> Any:
    if not np.isfinite(value).all():
        raise MessageError(f"value {value} is not finite")
    return value


def _reference(msgtype: str, shape: tuple[int, int] | None = (16, 16)) -> Callable[[bytes], Any]:
    """What the reader did before: rosbags objects and the message validators."""

    def read(data: bytes) -> tuple[int, Any]:
        msg = m.deserialize(data, msgtype)
        if msgtype == m.IMAGE_TYPE:
            value: Any = m.image_to_array(msg, shape=shape).tobytes()
        elif msgtype == m.ACTION_TYPE:
            value = m.twist_to_xy(msg)
        elif msgtype == m.POSE_TYPE:
            value = _finite(m.pose_to_xy(msg))
        else:
            value = _finite(m.reward_to_sample(msg).reward)
        if msg.header.stamp.sec < 0 or msg.header.stamp.nanosec >= S:  # not a time
            raise MessageError(f"header stamp {msg.header.stamp} is not a valid time")
        return m.stamp_of(msg), value

    return read


def _decoded(decoder: Any, data: bytes) -> tuple[int, Any]:
    stamp, value = decoder.decode(data)
    return stamp, bytes(value) if isinstance(value, memoryview) else value


def _messages(msgtype: str, frame: str, k: int) -> Any:
    rng = np.random.default_rng(k)
    stamp = k * S + int(rng.integers(S))
    if msgtype == m.IMAGE_TYPE:
        return m.image_msg(stamp, rng.integers(0, 256, (16, 16, 3), dtype=np.uint8), frame)
    if msgtype == m.ACTION_TYPE:
        return m.twist_stamped_msg(stamp, *rng.normal(size=2), frame_id=frame)
    if msgtype == m.POSE_TYPE:
        return m.pose_msg(stamp, *rng.normal(size=2), frame_id=frame)
    sample = m.RewardSample(float(rng.normal()), bool(k % 2), bool(k % 3))
    return m.reward_msg(stamp, sample, frame_id=frame)


DECODERS = {
    m.IMAGE_TYPE: lambda: ImageDecoder((16, 16)),
    m.ACTION_TYPE: TwistDecoder,
    m.POSE_TYPE: PoseDecoder,
    m.REWARD_TYPE: RewardDecoder,
}


@pytest.mark.parametrize("msgtype", list(DECODERS))
@pytest.mark.parametrize("little", [True, False], ids=["little-endian", "big-endian"])
def test_decoders_equal_rosbags_for_every_frame_id_length_and_byte_order(msgtype, little):
    decoder, reference = DECODERS[msgtype](), _reference(msgtype)
    # runs of one layout (read the fast way after the first) and changes of layout
    for frame in [*FRAMES, *FRAMES[::-1]]:
        for k in range(3):
            data = _cdr(_messages(msgtype, frame, k), msgtype, little)
            assert _decoded(decoder, data) == reference(data), (frame, k)


def test_the_is_bigendian_flag_of_an_rgb8_image_changes_nothing_but_the_layout():
    decoder, reference = ImageDecoder((16, 16)), _reference(m.IMAGE_TYPE)
    for k, flag in enumerate([0, 1, 1, 0]):
        msg = _messages(m.IMAGE_TYPE, "camera", k)
        msg.is_bigendian = flag
        for little in (True, False):
            data = _cdr(msg, m.IMAGE_TYPE, little)
            assert _decoded(decoder, data) == reference(data)


def test_images_of_any_size_when_no_shape_is_given():
    for k, (height, width) in enumerate([(1, 1), (3, 5), (7, 2)]):
        decoder = ImageDecoder(None)
        pixels = np.arange(height * width * 3, dtype=np.uint8).reshape(height, width, 3) + k
        stamp, view = decoder.decode(m.serialize(m.image_msg(k, pixels), m.IMAGE_TYPE))
        assert stamp == k and bytes(view) == pixels.tobytes()
        assert decoder.shape == (height, width)
    # the first image's size is then required of the rest
    other = m.serialize(m.image_msg(9, np.zeros((2, 7, 3), np.uint8)), m.IMAGE_TYPE)
    with pytest.raises(MessageError, match="image is 2x7, expected 7x2"):
        decoder.decode(other)


def _image_bytes(**changes: Any) -> bytes:
    msg = m.image_msg(5 * S, np.full((16, 16, 3), 9, np.uint8))
    for name, value in changes.items():
        setattr(msg, name, value)
    return m.serialize(msg, m.IMAGE_TYPE)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"encoding": "bgr8"}, "image encoding 'bgr8' is not rgb8"),
        ({"encoding": "rgb8 "}, "image encoding 'rgb8 ' is not rgb8"),
        ({"height": 15}, "image is 15x16, expected 16x16"),
        ({"step": 47}, "image step 47 does not match width 16 x 3 bytes"),
        ({"data": np.zeros(16 * 16 * 3 - 1, np.uint8)}, "image holds 767 bytes, expected 768"),
    ],
)
def test_images_that_break_a_rule_are_refused_after_a_good_layout_was_learnt(changes, message):
    decoder = ImageDecoder((16, 16))
    decoder.decode(_image_bytes())
    with pytest.raises(MessageError, match=message):
        decoder.decode(_image_bytes(**changes))
    assert bytes(decoder.decode(_image_bytes())[1]) == bytes([9]) * 768  # still reads good ones


def test_hostile_cdr_bytes_are_refused_with_a_message_error():
    good = _image_bytes()
    decoder = ImageDecoder((16, 16))
    decoder.decode(good)
    data_length = len(good) - 768 - 4  # the uint32 length of the pixel sequence
    hostile = {
        "truncated": good[:-1],
        "empty": b"",
        "not CDR": b"\x01\x00" + good[2:],
        "pixels claimed beyond the end": good[:data_length]
        + (769).to_bytes(4, "little")
        + good[data_length + 4 :],
        "frame_id longer than the message": good[:12] + (2**31).to_bytes(4, "little") + good[16:],
        "frame_id not UTF-8": good[:16] + b"\xff" + good[17:],
        "frame_id without its terminator": good[:22] + b"x" + good[23:],
        "bytes after the message": good + bytes(4),
    }
    for name, data in hostile.items():
        with pytest.raises(MessageError):
            decoder.decode(data)
            pytest.fail(name)


@pytest.mark.parametrize("msgtype", list(DECODERS))
def test_mutated_messages_are_read_or_refused_exactly_as_rosbags_does(msgtype):
    # seeded byte mutations of a message whose layout the decoder has learnt: each is
    # either refused by both or read to the same stamp and value; nothing else is raised
    reference = _reference(msgtype)
    original = _cdr(_messages(msgtype, "camera", 1), msgtype, True)
    rng = np.random.default_rng(18)
    outcomes = {"read": 0, "refused": 0}
    decoder = DECODERS[msgtype]()
    decoder.decode(original)
    for _ in range(300):
        data = mutate(original, rng)
        try:
            expected = reference(data)
        except MessageError:
            with pytest.raises(MessageError):
                decoder.decode(data)
            outcomes["refused"] += 1
            continue
        assert _decoded(decoder, data) == expected
        outcomes["read"] += 1
    assert outcomes["read"] > 10 and outcomes["refused"] > 10, outcomes


def test_non_finite_values_are_refused_the_fast_way_too():
    decoder = TwistDecoder()
    decoder.decode(m.serialize(m.twist_stamped_msg(S, 3.0, 0.0), m.ACTION_TYPE))
    with pytest.raises(MessageError, match=r"velocity \(inf, 0.0\) is not finite"):
        decoder.decode(m.serialize(m.twist_stamped_msg(S, math.inf, 0.0), m.ACTION_TYPE))
    decoder = RewardDecoder()
    decoder.decode(m.serialize(m.reward_msg(S, m.RewardSample(1.0, False, False)), m.REWARD_TYPE))
    with pytest.raises(MessageError, match="value nan is not finite"):
        sample = m.RewardSample(math.nan, False, False)
        decoder.decode(m.serialize(m.reward_msg(S, sample), m.REWARD_TYPE))
    names = m.serialize(m.state_msg(S, np.zeros(3)), m.STATE_TYPE)  # a JointState, other names
    with pytest.raises(MessageError, match="reward message names"):
        decoder.decode(names)


@pytest.mark.parametrize("stamp", [(1, S), (-1, 0)])
def test_a_stamp_that_is_not_a_time_is_refused_on_both_paths(stamp):
    # (1 s, 10^9 ns) would pair with (2 s, 0 ns) as the same step
    decoder = TwistDecoder()
    good = m.twist_stamped_msg(S, 0.25, 0.0)
    decoder.decode(m.serialize(good, m.ACTION_TYPE))  # layout learnt: the next is fast
    bad = m.twist_stamped_msg(S, 0.25, 0.0)
    bad.header.stamp.sec, bad.header.stamp.nanosec = stamp
    for fresh in (False, True):
        with pytest.raises(MessageError, match="is not a valid time"):
            (TwistDecoder() if fresh else decoder).decode(m.serialize(bad, m.ACTION_TYPE))


def test_a_learnt_layout_is_read_without_deserialising_again(monkeypatch):
    # the fast path is taken: one rosbags deserialisation per layout, not per message
    import tpsr_ros.io.cdr_fields as cdr_fields

    calls: list[int] = []
    real = cdr_fields.deserialize
    monkeypatch.setattr(cdr_fields, "deserialize", lambda d, t: calls.append(1) or real(d, t))
    for msgtype, decoder in DECODERS.items():
        calls.clear()
        fresh = decoder()
        for k in range(5):
            fresh.decode(_cdr(_messages(msgtype, "camera", k), msgtype, True))
        assert len(calls) == 1, msgtype


def test_peek_stamp():
    data = m.serialize(m.twist_stamped_msg(3 * S + 7, 0, 0), m.ACTION_TYPE)
    assert peek_stamp(data) == 3 * S + 7
    assert peek_stamp(data[:11]) is None and peek_stamp(b"\x01" + data[1:]) is None


def _raw_image_cases() -> list[tuple[Any, str]]:
    """Raw images of every encoding (16-bit in both byte orders), odd frame_ids and sizes."""
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, size=(6, 10, 3), dtype=np.uint8)
    deep = rng.integers(0, 2**16, size=(3, 7, 1)).astype("<u2")
    alpha = np.full((6, 10, 1), 7, np.uint8)
    cases = [
        raw_msg(rgb, "rgb8"),
        raw_msg(rgb, "bgr8"),
        raw_msg(np.concatenate([rgb, alpha], axis=2), "rgba8"),
        raw_msg(np.concatenate([rgb, alpha], axis=2), "bgra8"),
        raw_msg(rgb[:, :, :1], "mono8"),
        raw_msg(rgb[:5, :3, :1], "8UC1"),
        raw_msg(deep, "mono16"),
        raw_msg(deep.astype(">u2"), "16UC1", is_bigendian=1),
    ]
    out = []
    for k, msg in enumerate(cases):
        msg.header.frame_id = FRAMES[k % len(FRAMES)]
        out.append((msg, msg.encoding))
    return out


@pytest.mark.parametrize("little", [True, False], ids=["little-endian", "big-endian"])
def test_raw_images_of_every_encoding_decode_as_decode_image_does(little):
    decoder = RawImageDecoder()
    for msg, encoding in _raw_image_cases() * 2:  # twice: the second time the fast way
        data = _cdr(msg, m.IMAGE_TYPE, little)
        expected = decode_image(m.deserialize(data, m.IMAGE_TYPE), m.IMAGE_TYPE)
        stamp, pixels = decoder.decode(data)
        assert stamp == S and pixels.dtype == expected.dtype, encoding
        np.testing.assert_array_equal(pixels, expected, err_msg=encoding)


@pytest.mark.parametrize(
    ("changes", "rule"),
    [
        ({"encoding_": "yuv422"}, "encoding 'yuv422' is not one of"),
        ({"step": 29}, "step 29 is less than width 10 x 3 bytes"),
        ({"step": 31}, "holds 180 bytes, expected 6 x 31"),
        ({"data": np.zeros(17, np.uint8)}, "holds 17 bytes, expected 6 x 30"),
        ({"width": 0}, "image size 6x0 is empty"),
    ],
)
def test_raw_images_breaking_a_rule_are_refused_as_decode_image_refuses(changes, rule):
    decoder = RawImageDecoder()
    rgb = np.zeros((6, 10, 3), np.uint8)
    decoder.decode(m.serialize(raw_msg(rgb, "rgb8"), m.IMAGE_TYPE))
    changes = dict(changes)
    encoding = changes.pop("encoding_", "rgb8")
    with pytest.raises(MessageError, match=rule):
        decoder.decode(m.serialize(raw_msg(rgb, encoding, **changes), m.IMAGE_TYPE))


def test_mutated_raw_images_are_read_or_refused_exactly_as_decode_image_does():
    msg = raw_msg(np.random.default_rng(3).integers(0, 256, (6, 10, 3), dtype=np.uint8), "bgr8")
    original = m.serialize(msg, m.IMAGE_TYPE)
    decoder, rng = RawImageDecoder(), np.random.default_rng(19)
    decoder.decode(original)
    outcomes = {"read": 0, "refused": 0}
    for _ in range(300):
        data = mutate(original, rng)
        try:
            expected = decode_image(m.deserialize(data, m.IMAGE_TYPE), m.IMAGE_TYPE)
        except MessageError:
            with pytest.raises(MessageError):
                decoder.decode(data)
            outcomes["refused"] += 1
            continue
        pixels = decoder.decode(data)[1]
        assert pixels.dtype == expected.dtype
        np.testing.assert_array_equal(pixels, expected)
        outcomes["read"] += 1
    assert outcomes["read"] > 10 and outcomes["refused"] > 10, outcomes
