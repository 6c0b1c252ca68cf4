"""Rebuild a readable bag from one whose recorder was killed hard or whose file is damaged.

    python -m tpsr_ros.bag_recover BAG [--keep-original]

A recorder killed with SIGKILL (or a power cut) leaves ``BAG/BAG.mcap`` truncated: it has
no summary section, and no ``metadata.yaml`` was written. The recorder flushes the bag
every second, closing an MCAP chunk each time, so the file holds complete chunks up to
the last flush followed by at most one partial record.

Recovery never loses what it was given:

- It walks the file's top-level records itself (opcode, length, body) and parses each
  with the ``mcap`` library (CRCs checked where the file has them). A record that does not
  parse is *skipped*, not the end: the scan resumes at the next byte where a whole chunk
  parses, so one damaged chunk costs that chunk only. Every skipped byte range is
  reported.
- Schemas, channels and messages are copied through as raw records, whatever their type:
  types outside ROS 2 Jazzy, channels without a schema (valid MCAP) and any message
  encoding keep their bytes. The recovered file is written by the ``mcap`` writer, with
  chunk and data CRCs, plus a rosbag2 ``metadata.yaml``.
- The result is verified: read back with the ``mcap`` reader, it must hold exactly the
  messages copied, topic by topic. Only then is the original removed, and only if
  nothing but an incomplete final record (the normal end of a killed recording) was
  skipped and ``--keep-original`` was not given; otherwise it stays beside the result as
  ``<file>.mcap.damaged``. A bag that already has ``metadata.yaml`` is left untouched.
"""

from __future__ import annotations

import io
import mmap
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from tpsr_ros.cli import ArgumentParser, run_cli
from tpsr_ros.core.errors import BagError
from tpsr_ros.io.bag import rosbag2_metadata

__all__ = ["RecoveryReport", "main", "recover_bag"]

PROG = "python -m tpsr_ros.bag_recover"
_MAGIC = b"\x89MCAP0\r\n"
_CHUNK = 0x06
_HEADER = struct.Struct("<BQ")
_KEPT = (Schema, Channel, Message, Metadata, Attachment)


@dataclass(frozen=True)
class RecoveryReport:
    """What a recovery kept, what it had to skip, and where the original went."""

    path: Path
    messages: int
    topics: dict[str, int]
    skipped: tuple[tuple[int, int], ...] = ()  # damaged byte ranges [start, end) of the file
    truncated_tail: bool = False  # the file ended inside a record (a killed recorder)
    original: Path | None = None  # where the original file was kept, if it was

    @property
    def stopped_early(self) -> str | None:
        """A one-line account of the loss, or None when nothing was lost."""
        parts = [f"{end - start} damaged bytes at offset {start}" for start, end in self.skipped]
        if self.truncated_tail:
            parts.append("an incomplete final record")
        return "; ".join(parts) or None


@dataclass
class _Scan:
    """Records found in the file, with what could not be read."""

    records: list[Any] = field(default_factory=list)
    skipped: list[tuple[int, int]] = field(default_factory=list)
    truncated_tail: bool = False


def _mcap_file(bag: Path) -> Path:
    if not bag.is_dir():
        raise BagError(f"{str(bag)!r} is not a bag directory")
    files = sorted(p for p in bag.iterdir() if p.suffix == ".mcap" and p.is_file())
    if len(files) != 1:
        raise BagError(f"{str(bag)!r} holds {len(files)} .mcap files; expected exactly one")
    return files[0]


def _parse_at(data: mmap.mmap | bytes, offset: int) -> tuple[list[Any], int] | None:
    """The records of the top-level record at ``offset`` and its end, or None if damaged."""
    if offset + _HEADER.size > len(data):
        return None
    _, length = _HEADER.unpack_from(data, offset)
    end = offset + _HEADER.size + length
    if end > len(data):
        return None
    body = io.BytesIO(data[offset:end])
    records: list[Any] = []
    try:
        for record in StreamReader(body, skip_magic=True, validate_crcs=True).records:
            records.append(record)
    except EndOfFile:  # how the stream reader says it consumed the one record
        pass
    except Exception:  # the mcap library raises many types for damaged bytes
        return None
    return (records, end) if records else None


def _next_chunk(data: mmap.mmap | bytes, start: int) -> int | None:
    """The first offset from ``start`` at which a whole chunk record parses."""
    offset = data.find(bytes([_CHUNK]), start)
    while offset != -1:
        if _parse_at(data, offset) is not None:
            return offset
        offset = data.find(bytes([_CHUNK]), offset + 1)
    return None


def _scan(data: mmap.mmap | bytes) -> _Scan:
    """Every intact top-level record, resuming after damage at the next intact chunk."""
    scan = _Scan()
    offset = len(_MAGIC) if data[: len(_MAGIC)] == _MAGIC else 0
    if offset == 0:
        resumed = _next_chunk(data, 0)
        if resumed is None:
            raise BagError("no MCAP magic and no intact chunk: not a recoverable MCAP file")
        scan.skipped.append((0, resumed))
        offset = resumed
    while offset < len(data):
        if data[offset:] == _MAGIC:  # the closing magic of a complete file
            break
        parsed = _parse_at(data, offset)
        if parsed is None:
            resumed = _next_chunk(data, offset + 1)
            if resumed is None:
                tail_record = offset + _HEADER.size > len(data) or (
                    offset + _HEADER.size + _HEADER.unpack_from(data, offset)[1] > len(data)
                )
                if tail_record:
                    scan.truncated_tail = True
                else:
                    scan.skipped.append((offset, len(data)))
                break
            scan.skipped.append((offset, resumed))
            offset = resumed
            continue
        records, offset = parsed
        scan.records.extend(r for r in records if isinstance(r, _KEPT))
    return scan


def _metadata_yaml(
    file_name: str,
    channels: dict[int, Channel],
    schemas: dict[int, Schema],
    counts: dict[int, int],
    times: tuple[int, int],
) -> str:
    """rosbag2 ``metadata.yaml`` for the recovered file (types from the schemas)."""
    topics = []
    for channel_id, channel in channels.items():
        schema = schemas.get(channel.schema_id)
        topics.append(
            {
                "name": channel.topic,
                "type": schema.name if schema is not None else "",
                "serialization_format": channel.message_encoding,
                "offered_qos_profiles": channel.metadata.get("offered_qos_profiles", ""),
                "type_description_hash": channel.metadata.get("topic_type_hash", ""),
                "message_count": counts.get(channel_id, 0),
            }
        )
    return rosbag2_metadata(file_name, topics, times, {"tpsr_ros.recovered": "true"})


def _write(records: list[Any], target: Path) -> tuple[dict[str, int], str]:
    """Copy ``records`` into a new MCAP file; per-topic counts and ``metadata.yaml`` text."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    schema_ids: dict[int, int] = {0: 0}
    channel_ids: dict[int, int] = {}
    counts: dict[int, int] = {}
    first, last = 2**63 - 1, 0
    with target.open("wb") as handle:
        writer = Writer(handle, enable_data_crcs=True)
        writer.start(profile="ros2", library="tpsr_ros.bag_recover")
        for record in records:
            if isinstance(record, Schema) and record.id not in schema_ids:
                schemas[record.id] = record
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.id not in channel_ids:
                if record.schema_id not in schema_ids:
                    continue  # its schema was in a damaged range: no type to write it with
                channels[record.id] = record
                channel_ids[record.id] = writer.register_channel(
                    record.topic,
                    record.message_encoding,
                    schema_ids[record.schema_id],
                    dict(record.metadata),
                )
            elif isinstance(record, Message) and record.channel_id in channel_ids:
                writer.add_message(
                    channel_ids[record.channel_id],
                    record.log_time,
                    record.data,
                    record.publish_time,
                    record.sequence,
                )
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                first, last = min(first, record.log_time), max(last, record.log_time)
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                writer.add_attachment(
                    record.create_time,
                    record.log_time,
                    record.name,
                    record.media_type,
                    record.data,
                )
        writer.finish()
    topics: dict[str, int] = {}
    for channel_id, channel in channels.items():
        topics[channel.topic] = topics.get(channel.topic, 0) + counts.get(channel_id, 0)
    times = (first, last) if counts else (0, 0)
    return topics, _metadata_yaml(target.name, channels, schemas, counts, times)


def _verify(target: Path, expected: dict[str, int]) -> None:
    """Read the written file back; it must hold exactly ``expected`` messages per topic."""
    found: dict[str, int] = {}
    try:
        with target.open("rb") as handle:
            for _, channel, _ in make_reader(handle).iter_messages():
                found[channel.topic] = found.get(channel.topic, 0) + 1
    except (McapError, ValueError, OSError) as exc:
        raise BagError(f"the recovered file does not read back ({exc}); original kept") from None
    if {t: n for t, n in found.items() if n} != {t: n for t, n in expected.items() if n}:
        raise BagError(
            f"the recovered file reads back {found}, not the {expected} written; original kept"
        )


def recover_bag(bag: Path | str, *, keep_original: bool = False) -> RecoveryReport:
    """Rebuild ``bag`` in place from its truncated or damaged MCAP file."""
    bag = Path(bag).resolve()
    if (bag / "metadata.yaml").is_file():
        raise BagError(f"{str(bag)!r} already has metadata.yaml; nothing to recover")
    source = _mcap_file(bag)
    kept = source.with_name(source.name + ".damaged")
    if kept.exists():
        raise BagError(f"{str(kept)!r} exists: a previous recovery kept it; move it away first")
    if source.stat().st_size == 0:
        raise BagError(f"{str(source)!r} is empty: nothing to recover")
    with (
        source.open("rb") as handle,
        mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data,
    ):
        scan = _scan(data)
    with tempfile.TemporaryDirectory(prefix=".recovering-", dir=bag) as work:
        written = Path(work) / source.name
        topics, metadata_text = _write(scan.records, written)
        _verify(written, topics)
        source.rename(kept)  # the original is never overwritten; written replaces it
        written.rename(source)
        (bag / "metadata.yaml").write_text(metadata_text)
    report = RecoveryReport(
        bag, sum(topics.values()), topics, tuple(scan.skipped), scan.truncated_tail, kept
    )
    if not keep_original and not scan.skipped:
        kept.unlink()  # verified, and only an incomplete final record was lost
        report = RecoveryReport(bag, report.messages, topics, (), scan.truncated_tail, None)
    return report


def main(argv: list[str] | None = None) -> int:
    """Recover one bag and print what it holds, what was lost and where the original is."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("bag", type=Path, help="bag directory without metadata.yaml")
    parser.add_argument(
        "--keep-original", action="store_true", help="keep the original file as .damaged"
    )
    args = parser.parse_args(argv)
    report = recover_bag(args.bag, keep_original=args.keep_original)
    print(f"recovered {report.messages} messages on {len(report.topics)} topics into {args.bag}")
    for topic, count in sorted(report.topics.items()):
        print(f"  {topic}: {count}")
    if report.stopped_early:
        print(f"  lost: {report.stopped_early}")
    if report.original is not None:
        print(f"  the original file is kept as {report.original}")
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
