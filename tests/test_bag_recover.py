"""bag_recover never loses what it was given: every message the mcap
reader can read is kept, whatever its type; a damaged chunk costs that chunk only; the
original is deleted only when the result is verified and nothing but a truncated final
record was lost."""

from __future__ import annotations

import io
import itertools
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

from tpsr_ros.bag_recover import recover_bag
from tpsr_ros.core.errors import BagError
from tpsr_ros.io.safe_yaml import load_yaml

STRING_SCHEMA = b"string data\n"


def _write_mcap(path: Path, *, chunking=True, compression=CompressionType.ZSTD, summary=True,
                crcs=True, messages=40, chunk_size=1024) -> dict[str, int]:
    """A bag file with a Jazzy type, a type outside Jazzy, a schemaless channel, metadata and
    an attachment; returns the messages per topic."""
    with path.open("wb") as handle:
        writer = Writer(handle, chunk_size=chunk_size, compression=compression,
                        use_chunking=chunking, use_summary_offsets=summary,
                        use_statistics=summary, enable_crcs=crcs,
                        index_types=IndexType.ALL if summary else IndexType.NONE)
        writer.start(profile="ros2", library="test")
        string = writer.register_schema("std_msgs/msg/String", "ros2msg", STRING_SCHEMA)
        custom = writer.register_schema("acme_msgs/msg/Gizmo", "ros2msg", b"float64 torque\n")
        channels = {
            "/chatter": writer.register_channel("/chatter", "cdr", string),
            "/gizmo": writer.register_channel("/gizmo", "cdr", custom),
            "/raw": writer.register_channel("/raw", "json", 0),  # no schema: valid MCAP
        }
        counts = dict.fromkeys(channels, 0)
        for k, topic in zip(range(messages), itertools.cycle(channels), strict=False):
            payload = b"\x00\x01\x00\x00" + (8).to_bytes(4, "little") + b"message\x00"
            if topic == "/raw":
                payload = b'{"k": %d}' % k
            writer.add_message(channels[topic], 1_000 + k, payload + bytes(64), 1_000 + k, k)
            counts[topic] += 1
        writer.add_metadata("run", {"robot": "rover"})
        writer.add_attachment(1, 1, "calibration.yaml", "text/yaml", b"k: 1\n")
        writer.finish()
    return counts


def _bag(tmp_path: Path, name: str = "run", **options) -> tuple[Path, dict[str, int]]:
    bag = tmp_path / name
    bag.mkdir()
    return bag, _write_mcap(bag / f"{name}.mcap", **options)


def _messages_in_chunk(data: bytes, chunk) -> int:
    end = chunk.chunk_start_offset + chunk.chunk_length
    stream = io.BytesIO(data[chunk.chunk_start_offset:end])
    count = 0
    try:
        for record in StreamReader(stream, skip_magic=True).records:
            count += isinstance(record, Message)
    except EndOfFile:
        pass
    return count


def _read_back(bag: Path) -> dict[str, int]:
    found: dict[str, int] = {}
    with (bag / f"{bag.name}.mcap").open("rb") as handle:
        for _, channel, _ in make_reader(handle).iter_messages():
            found[channel.topic] = found.get(channel.topic, 0) + 1
    return found


@pytest.mark.parametrize("chunking, compression, summary, crcs", [
    (True, CompressionType.ZSTD, True, True),
    (True, CompressionType.LZ4, False, True),
    (True, CompressionType.NONE, True, False),
    (False, CompressionType.NONE, False, False),
    (False, CompressionType.NONE, True, True),
])
def test_every_message_of_every_type_is_kept(tmp_path, chunking, compression, summary, crcs):
    bag, counts = _bag(tmp_path, chunking=chunking, compression=compression, summary=summary,
                       crcs=crcs)
    report = recover_bag(bag)
    assert report.topics == counts and report.messages == sum(counts.values())
    assert report.stopped_early is None and report.original is None
    assert _read_back(bag) == counts
    with (bag / "run.mcap").open("rb") as handle:
        reader = make_reader(handle)
        assert [m.name for m in reader.iter_metadata()] == ["run"]
        assert [a.name for a in reader.iter_attachments()] == ["calibration.yaml"]
    info = load_yaml((bag / "metadata.yaml").read_text(), "metadata")["rosbag2_bagfile_information"]
    assert {t["topic_metadata"]["name"]: t["message_count"]
            for t in info["topics_with_message_count"]} == counts
    assert info["relative_file_paths"] == ["run.mcap"] and info["message_count"] == 40


def test_a_damaged_chunk_costs_that_chunk_only_and_the_original_is_kept(tmp_path):
    bag, counts = _bag(tmp_path, messages=200, chunk_size=512)
    mcap = bag / "run.mcap"
    data = bytearray(mcap.read_bytes())
    with mcap.open("rb") as handle:
        chunks = list(make_reader(handle).get_summary().chunk_indexes)
    assert len(chunks) >= 8
    middle = chunks[len(chunks) // 2]
    lost = _messages_in_chunk(data, middle)
    data[middle.chunk_start_offset + middle.chunk_length - 20] ^= 0xFF  # inside its records
    mcap.write_bytes(bytes(data))
    report = recover_bag(bag)
    assert 0 < sum(counts.values()) - report.messages <= lost
    assert len(report.skipped) == 1 and report.skipped[0][0] == middle.chunk_start_offset
    # chunks after the damage are kept: the last message survives
    assert _read_back(bag) == report.topics and report.original == bag / "run.mcap.damaged"
    assert report.original.read_bytes() == bytes(data)  # the original, untouched


def test_a_killed_recording_loses_only_its_incomplete_last_record(tmp_path):
    bag, counts = _bag(tmp_path, messages=100, chunk_size=512)
    mcap = bag / "run.mcap"
    data = mcap.read_bytes()
    with mcap.open("rb") as handle:
        last = max(make_reader(handle).get_summary().chunk_indexes,
                   key=lambda c: c.chunk_start_offset)
    # cut the file in the middle of its last chunk, as SIGKILL during a flush would
    mcap.write_bytes(data[: last.chunk_start_offset + last.chunk_length // 2])
    result = subprocess.run([sys.executable, "-m", "tpsr_ros.bag_recover", str(bag)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "lost: an incomplete final record" in result.stdout
    assert not (bag / "run.mcap.damaged").exists()  # verified, nothing else lost: removed
    kept = sum(_read_back(bag).values())
    assert kept == sum(counts.values()) - _messages_in_chunk(data, last)


def test_bad_input_is_refused_without_touching_anything(tmp_path):
    bag, _ = _bag(tmp_path)
    (bag / "metadata.yaml").write_text("x: 1\n")
    with pytest.raises(BagError, match=r"already has metadata\.yaml"):
        recover_bag(bag)
    lfs = tmp_path / "lfs"
    lfs.mkdir()
    (lfs / "lfs.mcap").write_text("version https://git-lfs.github.com/spec/v1\n")
    with pytest.raises(BagError, match="not a recoverable MCAP file"):
        recover_bag(lfs)
    assert (lfs / "lfs.mcap").read_text().startswith("version")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="is empty"):
        recover_bag(empty)


def _chunks(path: Path) -> list:
    with path.open("rb") as handle:
        return sorted(make_reader(handle).get_summary().chunk_indexes,
                      key=lambda c: c.chunk_start_offset)


def test_a_split_bag_is_recovered_file_by_file_and_its_metadata_lists_them(tmp_path):
    # rosbag2 splits long recordings into <bag>_0.mcap, <bag>_1.mcap, ...; here the second
    # file has a damaged chunk, the third was cut by a kill, the fourth is not MCAP at all
    bag = tmp_path / "split"
    bag.mkdir()
    counts = [_write_mcap(bag / f"split_{i}.mcap", messages=120, chunk_size=512)
              for i in range(3)]
    (bag / "split_10.mcap").write_text("version https://git-lfs.github.com/spec/v1\n")
    intact = (bag / "split_1.mcap").read_bytes()
    damaged = bytearray(intact)
    middle = _chunks(bag / "split_1.mcap")[3]
    damaged[middle.chunk_start_offset + middle.chunk_length - 20] ^= 0xFF
    (bag / "split_1.mcap").write_bytes(bytes(damaged))
    whole = (bag / "split_2.mcap").read_bytes()
    last = _chunks(bag / "split_2.mcap")[-1]
    (bag / "split_2.mcap").write_bytes(whole[: last.chunk_start_offset + last.chunk_length // 2])

    report = recover_bag(bag)

    names = [f.name for f in report.files]
    assert names == ["split_0.mcap", "split_1.mcap", "split_2.mcap", "split_10.mcap"]
    first, second, third, junk = report.files
    assert first.topics == counts[0] and first.lost is None and first.original is None
    assert 0 < sum(counts[1].values()) - second.messages <= _messages_in_chunk(intact, middle)
    assert second.original == bag / "split_1.mcap.damaged"
    assert second.original.read_bytes() == bytes(damaged)  # unverifiable loss: kept
    assert third.lost == "an incomplete final record" and third.original is None
    assert third.messages == sum(counts[2].values()) - _messages_in_chunk(whole, last)
    assert junk.error is not None and "not a recoverable MCAP file" in junk.error
    assert (bag / "split_10.mcap.damaged").read_text().startswith("version")
    assert not (bag / "split_10.mcap").exists()
    info = load_yaml((bag / "metadata.yaml").read_text(), "metadata")["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == ["split_0.mcap", "split_1.mcap", "split_2.mcap"]
    assert [f["message_count"] for f in info["files"]] == [
        first.messages, second.messages, third.messages
    ]
    assert info["message_count"] == report.messages
    for entry in info["topics_with_message_count"]:
        name = entry["topic_metadata"]["name"]
        assert entry["message_count"] == sum(f.topics.get(name, 0) for f in report.files)
    for f in report.files[:3]:
        assert _read_back_file(bag / f.name) == f.topics


def _read_back_file(path: Path) -> dict[str, int]:
    found: dict[str, int] = {}
    with path.open("rb") as handle:
        for _, channel, _ in make_reader(handle).iter_messages():
            found[channel.topic] = found.get(channel.topic, 0) + 1
    return found


def test_a_split_bag_with_no_recoverable_file_is_left_untouched(tmp_path):
    bag = tmp_path / "junk"
    bag.mkdir()
    for i in range(2):
        (bag / f"junk_{i}.mcap").write_bytes(b"not mcap %d" % i)
    with pytest.raises(BagError, match="nothing recovered; every file left untouched"):
        recover_bag(bag)
    assert sorted(p.name for p in bag.iterdir()) == ["junk_0.mcap", "junk_1.mcap"]
    assert (bag / "junk_1.mcap").read_bytes() == b"not mcap 1"


def test_recovery_copies_in_bounded_memory(tmp_path):
    # a recorder killed after hours leaves a file of GB: recovery must stream it chunk by
    # chunk, not hold every message (here 6 MB of messages, chunks of 256 KiB)
    import tracemalloc

    bag = tmp_path / "big"
    bag.mkdir()
    with (bag / "big.mcap").open("wb") as handle:
        writer = Writer(handle, chunk_size=2**18, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", STRING_SCHEMA)
        channel = writer.register_channel("/chatter", "cdr", schema)
        payload = bytes(2000)
        for k in range(3000):
            writer.add_message(channel, k, payload, k, k)
        writer.finish()
    tracemalloc.start()
    try:
        report = recover_bag(bag)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert report.messages == 3000
    assert peak < 4 * 2**20, f"peak {peak / 2**20:.1f} MiB for a 6 MB file"


def test_damage_full_of_chunk_opcodes_is_skipped_without_parsing_each(tmp_path, monkeypatch):
    # damaged bytes made of 0x06 opcodes with lengths that stay inside the file: each is a
    # chunk candidate, and copying + parsing every one takes time quadratic in the damage
    import tpsr_ros.bag_recover as recover

    parsed: list[int] = []
    real_parse = recover._parse_at
    monkeypatch.setattr(recover, "_parse_at", lambda d, o: parsed.append(o) or real_parse(d, o))
    junk = (b"\x06" + (1000).to_bytes(8, "little")) * 600
    parses = {}
    for name in ("clean", "junk"):
        bag, counts = _bag(tmp_path, name, messages=200, chunk_size=512)
        mcap = bag / f"{name}.mcap"
        data = bytearray(mcap.read_bytes())
        if name == "junk":
            with mcap.open("rb") as handle:
                chunks = list(make_reader(handle).get_summary().chunk_indexes)
            start = chunks[len(chunks) // 2].chunk_start_offset
            data[start:start] = junk
            mcap.write_bytes(bytes(data))
        parsed.clear()
        report = recover_bag(bag)
        assert report.messages == sum(counts.values())  # the junk was inserted: nothing lost
        parses[name] = len(parsed)
    assert report.skipped == ((start, start + len(junk)),)
    # the 600 candidates are refused from their header fields (the old scan parsed 1200 more)
    assert parses["junk"] <= parses["clean"] + 10, parses
