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
- A bag split into several files (rosbag2's ``<bag>_0.mcap``, ``<bag>_1.mcap``, ...) is
  recovered file by file, each verified before anything changes; ``metadata.yaml`` lists
  them in order with their own counts and times. A file of which nothing can be
  recovered is kept as ``.damaged`` and left out of the list; when no file can be
  recovered, nothing is touched.
"""

from __future__ import annotations

import dataclasses
import io
import mmap
import re
import struct
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from tpsr_ros.cli import ArgumentParser, run_cli
from tpsr_ros.core.errors import BagError, one_line
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.bag import BagFile, rosbag2_metadata
from tpsr_ros.io.mcap_layout import MAGIC, MAX_CHUNK_BYTES, RECORD_HEADER

__all__ = ["FileRecovery", "RecoveryReport", "main", "recover_bag"]

PROG = "python -m tpsr_ros.bag_recover"
_CHUNK = 0x06
_KEPT = (Schema, Channel, Message, Metadata, Attachment)


def _record_end(data: mmap.mmap | bytes, offset: int) -> int | None:
    """Where the top-level record at ``offset`` ends, or None if it runs past the file."""
    if offset + RECORD_HEADER.size > len(data):
        return None
    _, length = RECORD_HEADER.unpack_from(data, offset)
    end = offset + RECORD_HEADER.size + length
    return end if end <= len(data) else None


def _parse_at(data: mmap.mmap | bytes, offset: int) -> tuple[list[Any], int] | None:
    """The records of the top-level record at ``offset`` and its end, or None if damaged."""
    end = _record_end(data, offset)
    if end is None:
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


def _chunk_fields_fit(data: mmap.mmap | bytes, offset: int) -> bool:
    """Whether a chunk record could start at ``offset``: its fields fit its declared length.

    Reads a few header fields only, so that scanning damaged bytes for the next chunk does
    not copy and parse a record body at every 0x06 byte (quadratic time on hostile files).
    A chunk body is start and end time, uncompressed size and CRC, the compression name
    (u32 length + bytes) and the records (u64 length + bytes).
    """
    end = _record_end(data, offset)
    if end is None or end - offset < RECORD_HEADER.size + 40:
        return False
    body = offset + RECORD_HEADER.size
    (uncompressed,) = struct.unpack_from("<Q", data, body + 16)
    (name_length,) = struct.unpack_from("<I", data, body + 28)
    if uncompressed > MAX_CHUNK_BYTES or name_length > 16 or body + 40 + name_length > end:
        return False
    (compressed,) = struct.unpack_from("<Q", data, body + 32 + name_length)
    return compressed <= end - body - 40 - name_length


def _next_chunk(data: mmap.mmap | bytes, start: int) -> int | None:
    """The first offset from ``start`` at which a whole chunk record parses."""
    offset = data.find(bytes([_CHUNK]), start)
    while offset != -1:
        if _chunk_fields_fit(data, offset) and _parse_at(data, offset) is not None:
            return offset
        offset = data.find(bytes([_CHUNK]), offset + 1)
    return None


class _Scan:
    """A walk over the file's intact top-level records, with what could not be read.

    :meth:`records` yields the kept records one top-level record (a chunk) at a time, so a
    file of any size is copied in bounded memory; ``skipped`` and ``truncated_tail`` are
    complete once it is exhausted.
    """

    def __init__(self, data: mmap.mmap | bytes) -> None:
        self.data = data
        self.skipped: list[tuple[int, int]] = []
        self.truncated_tail = False

    def records(self) -> Iterator[Any]:
        """Every intact record, resuming after damage at the next intact chunk."""
        data = self.data
        offset = len(MAGIC) if data[: len(MAGIC)] == MAGIC else 0
        if offset == 0:
            resumed = _next_chunk(data, 0)
            if resumed is None:
                raise BagError("no MCAP magic and no intact chunk: not a recoverable MCAP file")
            self.skipped.append((0, resumed))
            offset = resumed
        while offset < len(data):
            if len(data) - offset == len(MAGIC) and data[offset:] == MAGIC:  # closing magic
                break
            parsed = _parse_at(data, offset)
            if parsed is None:
                resumed = _next_chunk(data, offset + 1)
                if resumed is None:
                    if _record_end(data, offset) is None:  # the file ends inside it
                        self.truncated_tail = True
                    else:
                        self.skipped.append((offset, len(data)))
                    break
                self.skipped.append((offset, resumed))
                offset = resumed
                continue
            records, offset = parsed
            yield from (r for r in records if isinstance(r, _KEPT))


def _definitions(records: Iterable[Any]) -> tuple[dict[int, Schema], dict[int, Channel]]:
    """The first surviving copy of every schema and channel, wherever in the file it is."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    for record in records:
        if isinstance(record, Schema):
            schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            channels.setdefault(record.id, record)
    return schemas, channels


@dataclass(frozen=True)
class _Written:
    """One file copied and verified: its counts, channels' topic entries and times."""

    topics: dict[str, dict[str, Any]]  # topic name -> metadata.yaml topic entry (counted)
    times: tuple[int, int]
    messages: int
    orphans: int  # messages whose channel record was lost: no topic to write them on


def _topic_entry(channel: Channel, schema: Schema | None) -> dict[str, Any]:
    return {
        "name": channel.topic,
        "type": schema.name if schema is not None else "",
        "serialization_format": channel.message_encoding,
        "offered_qos_profiles": channel.metadata.get("offered_qos_profiles", ""),
        "type_description_hash": channel.metadata.get("topic_type_hash", ""),
        "message_count": 0,
    }


class _DefinitionLater(Exception):
    """A message's channel, or a channel's schema, is not (yet) known in a one-pass copy."""


def _write(
    records: Iterable[Any],
    definitions: tuple[dict[int, Schema], dict[int, Channel]] | None,
    target: Path,
) -> _Written:
    """Copy ``records`` into a new MCAP file, every message on its channel, raw.

    Schemas and channels come from ``definitions``, gathered from anywhere in the file (the
    summary section repeats them), so a damaged data-section schema or channel record costs
    nothing when its copy survives; a channel without any surviving schema is written
    schemaless. With ``definitions`` None they are gathered from ``records`` as they come
    (one pass, the usual case: each is written before its first use), and
    :class:`_DefinitionLater` is raised where one is needed before it was seen.
    """
    gathering = definitions is None
    schemas, channels = ({}, {}) if definitions is None else definitions
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    topics: dict[str, dict[str, Any]] = {}
    first, last, messages, orphans = 2**64 - 1, 0, 0, 0
    with target.open("wb") as handle:
        writer = Writer(handle, enable_data_crcs=True)
        writer.start(profile="ros2", library="tpsr_ros.bag_recover")

        def channel_id(source_id: int) -> int:
            if source_id not in channel_ids:
                channel = channels[source_id]
                if gathering and channel.schema_id not in schemas:
                    raise _DefinitionLater
                schema = schemas.get(channel.schema_id)
                if schema is not None and schema.id not in schema_ids:
                    schema_ids[schema.id] = writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
                channel_ids[source_id] = writer.register_channel(
                    channel.topic,
                    channel.message_encoding,
                    schema_ids[schema.id] if schema is not None else 0,
                    dict(channel.metadata),
                )
                topics.setdefault(channel.topic, _topic_entry(channel, schema))
            return channel_ids[source_id]

        for record in records:
            if gathering and isinstance(record, Schema):
                schemas.setdefault(record.id, record)
            elif gathering and isinstance(record, Channel):
                channels.setdefault(record.id, record)
            if isinstance(record, Channel) and record.id in channels:
                channel_id(record.id)
            elif isinstance(record, Message):
                if record.channel_id not in channels:
                    if gathering:
                        raise _DefinitionLater
                    orphans += 1
                    continue
                writer.add_message(
                    channel_id(record.channel_id),
                    record.log_time,
                    record.data,
                    record.publish_time,
                    record.sequence,
                )
                topics[channels[record.channel_id].topic]["message_count"] += 1
                messages += 1
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
    return _Written(topics, (first, last) if messages else (0, 0), messages, orphans)


def _verify(target: Path, written: _Written) -> None:
    """Read the written file back; it must hold exactly the messages written, per topic."""
    expected = {t: e["message_count"] for t, e in written.topics.items() if e["message_count"]}
    found: dict[str, int] = {}
    try:
        with target.open("rb") as handle:
            for _, channel, _ in make_reader(handle).iter_messages():
                found[channel.topic] = found.get(channel.topic, 0) + 1
    except (McapError, ValueError, OSError) as exc:
        raise BagError(
            f"the recovered file does not read back ({one_line(exc)}); original kept"
        ) from None
    if found != expected:
        raise BagError(
            f"the recovered file reads back {found}, not the {expected} written; original kept"
        )


@dataclass(frozen=True)
class FileRecovery:
    """What the recovery of one ``.mcap`` file of the bag kept and lost."""

    name: str
    messages: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    skipped: tuple[tuple[int, int], ...] = ()  # damaged byte ranges [start, end)
    truncated_tail: bool = False  # the file ended inside a record (a killed recorder)
    orphans: int = 0  # messages lost with their channel record
    original: Path | None = None  # where the original was kept, if it was
    error: str | None = None  # why nothing of this file could be recovered

    @property
    def lost(self) -> str | None:
        """A one-line account of the loss, or None when nothing was lost."""
        if self.error is not None:
            return f"nothing recovered ({self.error})"
        parts = [f"{end - start} damaged bytes at offset {start}" for start, end in self.skipped]
        if self.orphans:
            parts.append(f"{self.orphans} messages whose channel record was damaged")
        if self.truncated_tail:
            parts.append("an incomplete final record")
        return "; ".join(parts) or None


@dataclass(frozen=True)
class RecoveryReport:
    """What a recovery kept, file by file, and where the originals went."""

    path: Path
    files: tuple[FileRecovery, ...]

    @property
    def messages(self) -> int:
        """Messages in the recovered bag."""
        return sum(f.messages for f in self.files)

    @property
    def topics(self) -> dict[str, int]:
        """Messages per topic in the recovered bag."""
        totals: dict[str, int] = {}
        for f in self.files:
            for topic, count in f.topics.items():
                totals[topic] = totals.get(topic, 0) + count
        return totals

    @property
    def skipped(self) -> tuple[tuple[int, int], ...]:
        """Damaged byte ranges of every file (one file: its offsets)."""
        return tuple(r for f in self.files for r in f.skipped)

    @property
    def originals(self) -> tuple[Path, ...]:
        """The original files kept beside the result."""
        return tuple(f.original for f in self.files if f.original is not None)

    @property
    def original(self) -> Path | None:
        """The kept original of a one-file bag (the first kept, for several)."""
        return self.originals[0] if self.originals else None

    @property
    def stopped_early(self) -> str | None:
        """A one-line account of the loss, or None when nothing was lost."""
        if len(self.files) == 1:
            return self.files[0].lost
        parts = [f"{f.name}: {f.lost}" for f in self.files if f.lost]
        return "; ".join(parts) or None


def _file_key(path: Path) -> tuple[Any, ...]:
    """rosbag2 names split files ``<bag>_<index>.mcap``: order them by that index."""
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", path.name))


def _mcap_files(bag: Path) -> list[Path]:
    if not bag.is_dir():
        raise BagError(f"{str(bag)!r} is not a bag directory")
    files = sorted((p for p in bag.iterdir() if p.suffix == ".mcap" and p.is_file()),
                   key=_file_key)
    if not files:
        raise BagError(f"{str(bag)!r} holds no .mcap file")
    return files


def _recover_file(source: Path, work: Path) -> tuple[FileRecovery, _Written | None]:
    """Scan, copy and verify one file into ``work``; nothing in the bag is touched yet."""
    try:
        if source.stat().st_size == 0:
            raise BagError(f"{str(source)!r} is empty: nothing to recover")
        with (
            source.open("rb") as handle,
            mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data,
        ):
            scan = _Scan(data)
            try:  # one pass when every definition comes before its first use
                written = _write(scan.records(), None, work / source.name)
            except _DefinitionLater:  # else gather them from the whole file first
                definitions = _definitions(_Scan(data).records())
                scan = _Scan(data)
                written = _write(scan.records(), definitions, work / source.name)
        _verify(work / source.name, written)
    except BagError as exc:
        return FileRecovery(source.name, error=str(exc)), None
    topics = {t: e["message_count"] for t, e in written.topics.items()}
    recovery = FileRecovery(
        source.name, written.messages, topics, tuple(scan.skipped), scan.truncated_tail,
        written.orphans,
    )
    return recovery, written


def _merged_topics(written: list[_Written]) -> list[dict[str, Any]]:
    merged: dict[str, dict[str, Any]] = {}
    for w in written:
        for name, entry in w.topics.items():
            if name in merged:
                merged[name]["message_count"] += entry["message_count"]
            else:
                merged[name] = dict(entry)
    return list(merged.values())


def recover_bag(bag: Path | str, *, keep_original: bool = False) -> RecoveryReport:
    """Rebuild ``bag`` in place from its truncated or damaged MCAP file(s).

    Every ``.mcap`` file of the bag (rosbag2 splits long recordings into
    ``<bag>_0.mcap``, ``<bag>_1.mcap``, ...) is recovered on its own and verified before
    anything in the bag changes; then each original is swapped for its copy, kept as
    ``<file>.damaged`` unless it is verified and lost nothing but an incomplete final
    record. A file of which nothing can be recovered is kept as ``.damaged`` and not
    listed; ``metadata.yaml`` lists the recovered files in order.
    """
    bag = Path(bag).resolve()
    if (bag / "metadata.yaml").is_file():
        raise BagError(f"{str(bag)!r} already has metadata.yaml; nothing to recover")
    sources = _mcap_files(bag)
    for source in sources:
        kept = source.with_name(source.name + ".damaged")
        if kept.exists():
            raise BagError(
                f"{str(kept)!r} exists: a previous recovery kept it; move it away first"
            )
    results: list[tuple[Path, FileRecovery, _Written | None]] = []
    with tempfile.TemporaryDirectory(prefix=".recovering-", dir=bag) as work:
        for source in sources:
            results.append((source, *_recover_file(source, Path(work))))
        if all(written is None for _, _, written in results):
            reasons = "; ".join(f.error or "" for _, f, _ in results)
            raise BagError(f"nothing recovered; every file left untouched: {reasons}")
        files, bag_files, written_all = [], [], []
        for source, recovery, written in results:
            kept = source.with_name(source.name + ".damaged")
            source.rename(kept)  # the original is never overwritten
            if written is not None:
                (Path(work) / source.name).rename(source)
                bag_files.append(BagFile(source.name, *written.times, written.messages))
                written_all.append(written)
                if not keep_original and not recovery.skipped and not recovery.orphans:
                    kept.unlink()  # verified, and only an incomplete final record was lost
                    kept = None
            files.append(dataclasses.replace(recovery, original=kept))
        text = rosbag2_metadata(
            bag_files, _merged_topics(written_all), {"tpsr_ros.recovered": "true"}
        )
        with atomic_file(bag / "metadata.yaml", "w") as handle:
            handle.write(text)
    return RecoveryReport(bag, tuple(files))


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
    for file in report.files:
        if file.lost:
            where = "" if len(report.files) == 1 else f" in {file.name}"
            print(f"  lost{where}: {file.lost}")
    for original in report.originals:
        print(f"  the original file is kept as {original}")
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
