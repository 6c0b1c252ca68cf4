"""The shared bag module: round trips, refusals, flushing."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from tpsr_ros.core.errors import BagError
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader, BagWriter


def test_round_trip_of_messages_and_bytes(tmp_path):
    image = np.arange(768, dtype=np.uint8).reshape(16, 16, 3)
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic("/camera/image_raw", m.IMAGE_TYPE)
        writer.add_topic("/action", m.ACTION_TYPE)
        for k in range(1, 4):
            writer.write_message("/camera/image_raw", k * 10**9, m.image_msg(k * 10**9, image))
            raw = m.serialize(m.twist_stamped_msg(k * 10**9, 3.0, -6.0), m.ACTION_TYPE)
            writer.write("/action", k * 10**9, raw)
    with BagReader(tmp_path / "bag") as reader:
        assert reader.topics == {"/camera/image_raw": m.IMAGE_TYPE, "/action": m.ACTION_TYPE}
        assert reader.message_counts == {"/camera/image_raw": 3, "/action": 3}
        msgs = list(reader.messages())
        assert [x.log_time_ns for x in msgs] == [10**9, 10**9, 2 * 10**9, 2 * 10**9, 3e9, 3e9]
        images = [x.decode() for x in msgs if x.topic == "/camera/image_raw"]
        assert all(np.array_equal(m.image_to_array(i), image) for i in images)
        actions = [m.twist_to_xy(x.decode()) for x in reader.messages(["/action"])]
        assert actions == [(3.0, -6.0)] * 3
        assert [m.stamp_of(i) for i in images] == [10**9, 2 * 10**9, 3 * 10**9]


def test_writer_refuses_undeclared_and_clashing_topics(tmp_path):
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic("/a", m.ACTION_TYPE)
        with pytest.raises(BagError, match="already has type"):
            writer.add_topic("/a", m.IMAGE_TYPE)
        with pytest.raises(BagError, match="not declared"):
            writer.write("/b", 0, b"")


def test_reader_refuses_what_is_not_a_rosbag2_mcap_bag(tmp_path):
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        BagReader(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match=r"no metadata\.yaml"):
        BagReader(tmp_path / "empty")
    (tmp_path / "garbage").mkdir()
    (tmp_path / "garbage" / "metadata.yaml").write_text("just: [a, list")
    with pytest.raises(BagError, match="not rosbag2 metadata"):
        BagReader(tmp_path / "garbage")
    with Writer(tmp_path / "sqlite", version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        w.add_connection("/a", m.CLOCK_TYPE, typestore=m.jazzy_typestore())
    with pytest.raises(BagError, match=r"storage 'sqlite3', not mcap"):
        BagReader(tmp_path / "sqlite")


def test_flush_puts_complete_messages_on_disk(tmp_path):
    writer = BagWriter(tmp_path / "bag", compress=False).open()
    writer.add_topic("/clock", m.CLOCK_TYPE)
    mcap = tmp_path / "bag" / "bag.mcap"
    before = mcap.stat().st_size
    for k in range(100):
        writer.write_message("/clock", k, m.clock_msg(k))
    writer.flush()
    assert mcap.stat().st_size > before + 100 * 20  # the chunk reached the file
    writer.close()
    with BagReader(tmp_path / "bag") as reader:
        assert reader.message_counts == {"/clock": 100}


def test_aborted_writer_removes_its_bag(tmp_path):
    with pytest.raises(RuntimeError), BagWriter(tmp_path / "bag") as writer:
        writer.add_topic("/clock", m.CLOCK_TYPE)
        raise RuntimeError("boom")
    assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("compress", [False, True])
def test_a_flipped_bit_in_a_written_bag_is_reported_as_corruption(tmp_path, compress):
    # our chunks carry CRCs, as ROS 2's own bags do: damage is detected, not read silently
    from mcap.reader import make_reader

    bag = tmp_path / "bag"
    with BagWriter(bag, compress=compress) as writer:
        writer.add_topic("/clock", m.CLOCK_TYPE)
        for k in range(2000):
            writer.write_message("/clock", k, m.clock_msg(k))
    mcap = bag / "bag.mcap"
    with mcap.open("rb") as handle:
        chunk = make_reader(handle).get_summary().chunk_indexes[0]
    data = bytearray(mcap.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 30] ^= 0x10  # inside the records
    mcap.write_bytes(bytes(data))
    # uncompressed, only the CRC can tell; compressed, zstd or the CRC does
    expected = "damaged.*checksum" if not compress else "damaged"
    with BagReader(bag) as reader, pytest.raises(BagError, match=expected):
        for _ in reader.messages():
            pass
