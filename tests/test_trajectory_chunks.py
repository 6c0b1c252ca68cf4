"""Streamed reading: the chunks of iter_trajectory_chunks concatenate to read_trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_episodes import S, image_for, step_of, write_bag

from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import BagError, ConfigError, DataError, MessageError
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.io.trajectory import Topics, iter_trajectory_chunks, read_trajectory

FIELDS = ("stamps", "observations", "actions", "velocities", "positions", "rewards", "segments")


def _concatenated(chunks: list[Trajectory]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([getattr(c, name) for c in chunks]) for name in FIELDS}


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """Three bags: gaps and a missing action; a plain one; one without ground truth."""
    root = tmp_path_factory.mktemp("chunks")
    return [
        write_bag(root / "a", [*range(1, 12), *range(14, 30)], skip={("/action", 20)}),
        write_bag(root / "b", range(40, 54)),
        write_bag(root / "c", range(60, 69), skip={"/ground_truth/pose", "/reward"}),
    ]


@pytest.mark.parametrize("chunk_steps", [1, 7, 14, 10**6])
def test_chunks_concatenate_to_read_trajectory(bags, chunk_steps):
    whole = read_trajectory(bags)
    chunks = list(iter_trajectory_chunks(bags, chunk_steps=chunk_steps))
    assert all(0 < len(c) <= chunk_steps for c in chunks)
    joined = _concatenated(chunks)
    for name in FIELDS:
        np.testing.assert_array_equal(joined[name], getattr(whole, name), err_msg=name)
        assert joined[name].dtype == getattr(whole, name).dtype
    assert all(c.image_shape == whole.image_shape and c.n_actions == 25 for c in chunks)
    # one source per bag, on that bag's last chunk; a chunk never spans two bags
    assert [s for c in chunks for s in c.sources] == whole.sources
    bag_of_chunk = [np.searchsorted([40 * S, 60 * S], c.stamps[0], side="right") for c in chunks]
    for c, bag in zip(chunks, bag_of_chunk, strict=True):
        assert np.all(np.searchsorted([40 * S, 60 * S], c.stamps, side="right") == bag)
    last = [
        i
        for i in range(len(chunks))
        if i + 1 == len(chunks) or bag_of_chunk[i + 1] != bag_of_chunk[i]
    ]
    assert [i for i, c in enumerate(chunks) if c.sources] == last


def test_what_read_trajectory_reads_is_the_ground_truth_of_the_bags(bags):
    # independent of the reader: the steps written, minus the missing action, in order
    whole = read_trajectory(bags)
    steps = [*range(1, 12), *range(14, 20), *range(21, 30), *range(40, 54), *range(60, 69)]
    np.testing.assert_array_equal(whole.stamps, np.array(steps) * S)
    np.testing.assert_array_equal([step_of(o) for o in whole.observations], steps)
    # segments: 1-11 | 14-19 | 21-29 (bag a) | 40-53 (bag b) | 60-68 (bag c), numbered on
    np.testing.assert_array_equal(np.unique(whole.segments), np.arange(5))
    assert whole.segment_bounds() == [(0, 11), (11, 17), (17, 26), (26, 40), (40, 49)]
    assert [s["segments"] for s in whole.sources] == [3, 1, 1]
    assert [s["unpaired_messages"] for s in whole.sources] == [1, 0, 0]
    assert np.isnan(whole.positions[40:]).all() and np.isnan(whole.rewards[40:]).all()
    assert not np.isnan(whole.positions[:40]).any()


def test_a_bag_whose_steps_fill_whole_chunks_has_its_source_on_the_last(tmp_path):
    bag = write_bag(tmp_path / "a", range(1, 15))
    chunks = list(iter_trajectory_chunks([bag], chunk_steps=7))
    assert [len(c) for c in chunks] == [7, 7]
    assert chunks[0].sources == [] and chunks[1].sources[0]["steps"] == 14
    np.testing.assert_array_equal(chunks[1].segments, 0)  # one segment across the chunks


def _write_in_file_order(path, steps) -> None:
    """Each step's image and action, in the order given, with increasing log times."""
    with BagWriter(path) as writer:
        writer.add_topic("/camera/image_raw", m.IMAGE_TYPE)
        writer.add_topic("/action", m.ACTION_TYPE)
        for i, k in enumerate(steps):
            writer.write_message("/camera/image_raw", 2 * i, m.image_msg(k * S, image_for(k)))
            writer.write_message("/action", 2 * i + 1, m.twist_stamped_msg(k * S, 0, 0))


def test_messages_out_of_stamp_order_within_the_window_are_sorted(tmp_path):
    # stamps in the file in reverse blocks of 5: 5 4 3 2 1 10 9 8 7 6 ...
    _write_in_file_order(tmp_path / "a", [k for b in range(6) for k in range(5 * b + 5, 5 * b, -1)])
    for trajectory in (read_trajectory([tmp_path / "a"]), _read_with_window([tmp_path / "a"], 5)):
        np.testing.assert_array_equal(trajectory.stamps, np.arange(1, 31) * S)
        assert trajectory.segment_bounds() == [(0, 30)]
        np.testing.assert_array_equal([step_of(o) for o in trajectory.observations], range(1, 31))
    # with 4, stamp 1 (read after 5 4 3 2) is final at once and its action comes too late
    with pytest.raises(BagError, match=r"'/action', message 4 \(stamp 1000000000 ns\)"):
        _read_with_window([tmp_path / "a"], 4)


def test_large_images_get_smaller_chunks_and_a_shorter_window(tmp_path, monkeypatch):
    # the caps in bytes, scaled down: chunks of 5 steps of 16x16 float64 observations, and a
    # window of 16 stamps of 16x16 images (the smallest allowed); bag b comes in reverse
    # blocks of 20 stamps, beyond that window
    import tpsr_ros.io.trajectory as trajectory

    monkeypatch.setattr(trajectory, "CHUNK_BYTES", 5 * 8 * 16 * 16 * 3)
    monkeypatch.setattr(trajectory, "PENDING_BYTES", 1)
    bag = write_bag(tmp_path / "a", range(1, 30))
    chunks = list(iter_trajectory_chunks([bag], chunk_steps=100))
    assert [len(c) for c in chunks] == [5, 5, 5, 5, 5, 4]
    np.testing.assert_array_equal(_concatenated(chunks)["stamps"], np.arange(1, 30) * S)
    reversed_blocks = [k for b in range(2) for k in range(20 * b + 20, 20 * b, -1)]
    _write_in_file_order(tmp_path / "b", reversed_blocks)
    with pytest.raises(BagError, match="comes after messages of 16 or more later stamps"):
        read_trajectory([tmp_path / "b"])
    monkeypatch.setattr(trajectory, "PENDING_BYTES", 10**9)  # 16x16 images: the full window
    np.testing.assert_array_equal(read_trajectory([tmp_path / "b"]).stamps, np.arange(1, 41) * S)


def _read_with_window(bags, window: int) -> Trajectory:
    chunks = list(iter_trajectory_chunks(bags, reorder_window=window))
    return Trajectory(
        **_concatenated(chunks),
        image_shape=chunks[0].image_shape,
        n_actions=25,
        sources=[s for c in chunks for s in c.sources],
    )


def test_a_message_later_than_the_window_is_refused_naming_it(tmp_path):
    # step 1's action comes after the messages of stamps 2..12
    path = tmp_path / "late"
    topics = Topics()
    with BagWriter(path) as writer:
        writer.add_topic(topics.image, m.IMAGE_TYPE)
        writer.add_topic(topics.action, m.ACTION_TYPE)
        for k in range(1, 13):
            writer.write_message(
                topics.image, k * S, m.image_msg(k * S, np.zeros((16, 16, 3), np.uint8))
            )
            if k > 1:
                writer.write_message(topics.action, k * S, m.twist_stamped_msg(k * S, 0, 0))
        writer.write_message(topics.action, 13 * S, m.twist_stamped_msg(S, 0, 0))
    with pytest.raises(
        BagError,
        match=r"topic '/action', message 11 \(stamp 1000000000 ns\) "
        r"comes after messages of 4 or more later stamps",
    ):
        list(iter_trajectory_chunks([path], reorder_window=4))
    assert len(read_trajectory([path])) == 12  # within the default window


def test_chunks_stream_a_bag_rather_than_reading_it_whole(tmp_path):
    # a bad image at the end: the first chunks come out before the reader reaches it
    bad = {40: m.image_msg(40 * S, np.zeros((8, 8, 3), np.uint8))}
    bag = write_bag(
        tmp_path / "a",
        range(1, 41),
        image=lambda k: bad.get(k) or m.image_msg(k * S, np.zeros((16, 16, 3), np.uint8)),
        shuffle_log_times=False,
    )
    chunks = iter_trajectory_chunks([bag], chunk_steps=4, reorder_window=2)
    first = [next(chunks) for _ in range(5)]
    np.testing.assert_array_equal(np.concatenate([c.stamps for c in first]), np.arange(1, 21) * S)
    with pytest.raises(
        MessageError,
        match=r"topic '/camera/image_raw', message 39 \(stamp "
        r"40000000000 ns\): image is 8x8, expected 16x16",
    ):
        list(chunks)


def test_errors_name_the_bag_topic_and_stamp(tmp_path):
    bag = write_bag(tmp_path / "a", range(1, 4), velocity=lambda k: (float("nan"), 0.0))
    with pytest.raises(
        MessageError,
        match=r"'/action', message 0 \(stamp 1000000000 ns\): "
        r"velocity \(nan, 0.0\) is not finite",
    ):
        list(iter_trajectory_chunks([bag]))
    gt = write_bag(tmp_path / "b", range(1, 6), skip={("/reward", 3)})
    with pytest.raises(
        DataError,
        match=r"lacks ground truth for some steps: the step at stamp 3000000000 ns has no "
        r"message on '/reward'",
    ):
        read_trajectory([gt], require_ground_truth=True)
    no_actions = write_bag(tmp_path / "c", range(1, 4), skip={"/action"})
    with pytest.raises(BagError, match=r"no messages on topic\(s\) \['/action'\]"):
        list(iter_trajectory_chunks([no_actions]))
    with BagWriter(tmp_path / "d") as writer:  # images and actions that never share a stamp
        writer.add_topic("/camera/image_raw", m.IMAGE_TYPE)
        writer.add_topic("/action", m.ACTION_TYPE)
        writer.write_message(
            "/camera/image_raw", S, m.image_msg(S, np.zeros((16, 16, 3), np.uint8))
        )
        writer.write_message("/action", 2 * S, m.twist_stamped_msg(2 * S, 0, 0))
    with pytest.raises(
        DataError,
        match=r"no image and action with the same stamp \(1 images, "
        r"1 actions\)",
    ):
        list(iter_trajectory_chunks([tmp_path / "d"]))


def test_arguments_are_checked_when_called(tmp_path):
    with pytest.raises(ConfigError, match="no bag"):
        iter_trajectory_chunks([])
    with pytest.raises(ConfigError, match="chunk_steps must be at least 1"):
        iter_trajectory_chunks([tmp_path], chunk_steps=0)
    with pytest.raises(ConfigError, match="reorder_window"):
        iter_trajectory_chunks([tmp_path], reorder_window=0)


SAMPLE_BAGS = Path(__file__).resolve().parent.parent / "bags"


def _object_reader(bag: Path) -> dict[str, np.ndarray]:
    """The reader the chunked one replaced, kept as the reference: a rosbags object per message."""
    topics = Topics()
    data: dict[str, dict[int, object]] = {t: {} for t in topics.types()}
    with BagReader(bag) as reader:
        for msg in reader.messages(list(data)):
            obj = msg.decode()
            data[msg.topic][m.stamp_of(obj)] = obj
    images, actions = data[topics.image], data[topics.action]
    stamps = sorted(set(images) & set(actions))
    pose = data[topics.pose]
    reward = data[topics.reward]
    return {
        "stamps": np.array(stamps),
        "observations": np.stack([m.image_to_array(images[s]) for s in stamps]).reshape(
            len(stamps), -1
        )
        / 255.0,
        "velocities": np.array([m.twist_to_xy(actions[s]) for s in stamps]),
        "positions": np.array([m.pose_to_xy(pose[s]) for s in stamps]),
        "rewards": np.array([m.reward_to_sample(reward[s]).reward for s in stamps]),
    }


@pytest.mark.slow
def test_the_sample_bag_reads_as_with_a_rosbags_object_per_message():
    bag = SAMPLE_BAGS / "full"
    expected = _object_reader(bag)
    chunks = list(iter_trajectory_chunks([bag], chunk_steps=1000))
    whole = read_trajectory([bag])
    for name, values in expected.items():
        np.testing.assert_array_equal(getattr(whole, name), values, err_msg=name)
        np.testing.assert_array_equal(_concatenated(chunks)[name], values, err_msg=name)


def test_a_topic_with_connections_of_two_types_is_refused(tmp_path):
    # an AccelStamped connection and a TwistStamped one on /action: decoding the first's
    # bytes as twists would read accelerations as velocities, silently
    from rosbags.rosbag2 import StoragePlugin, Writer

    typestore = m.jazzy_typestore()
    accel = "geometry_msgs/msg/AccelStamped"
    vector = typestore.types["geometry_msgs/msg/Vector3"]
    path = tmp_path / "mixed"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        image = writer.add_connection("/camera/image_raw", m.IMAGE_TYPE, typestore=typestore)
        wrong = writer.add_connection("/action", accel, typestore=typestore)
        writer.add_connection("/action", m.ACTION_TYPE, typestore=typestore)
        for k in range(1, 6):
            pixels = np.zeros((16, 16, 3), np.uint8)
            writer.write(image, k * S, m.serialize(m.image_msg(k * S, pixels), m.IMAGE_TYPE))
            msg = typestore.types[accel](
                header=m.header_msg(k * S, "x"),
                accel=typestore.types["geometry_msgs/msg/Accel"](
                    linear=vector(x=0.25, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.0)
                ),
            )
            writer.write(wrong, k * S + 1, bytes(typestore.serialize_cdr(msg, accel)))
    with pytest.raises(BagError, match="topic '/action' has messages of two types"):
        read_trajectory([path])
