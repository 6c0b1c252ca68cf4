"""The MCAP conformance files (foxglove/mcap ``tests/conformance/data``), built at test time.

The conformance suite's 416 ``.mcap`` files are generated from six small inputs
(``tests/conformance/variants/inputs.ts``) under every sensible combination of ten
writer features (``generateTestVariants.ts``), by ``scripts/generate-inputs.ts``. This
module ports those three files to Python on top of the ``mcap`` library's record classes
(each record's ``write`` into a ``RecordBuilder``), so the files need not be stored here.

``tests/data/mcap_conformance_crcs.json`` holds, for every variant, the two CRCs its
``.json`` twin in the conformance suite records: the ``DataEnd`` record's data-section CRC
and the ``Footer``'s summary CRC. Together they cover every byte of the file but the
magic, so a generated file whose two CRCs match is the conformance file. Rebuild that
table from a checkout of foxglove/mcap with ``python tests/mcap_conformance.py MCAP_REPO``.

Inputs and generator: Copyright (c) Foxglove Technologies Inc, MIT License.
"""

from __future__ import annotations

import json
import struct
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

CRCS = Path(__file__).resolve().parent / "data" / "mcap_conformance_crcs.json"
MAGIC = b"\x89MCAP0\r\n"
# TestFeatures, in the order of types.ts (the order the variants are enumerated in)
FEATURES = ("ch", "mx", "st", "rsh", "rch", "ax", "mdx", "chx", "sum", "pad")
_PAD = b"\x01\xff\xff"  # McapRecordBuilder's padRecords: three extra bytes
_UNPADDED = {Opcode.MESSAGE, Opcode.CHUNK, Opcode.DATA_END, Opcode.FOOTER}


def _ten_messages() -> list[McapRecord]:
    return [
        Message(channel_id=1, sequence=i, log_time=t, publish_time=t, data=bytes([1, 2, 3]))
        for i, t in enumerate([0, 2, 1, 3, 3, 5, 4, 7, 8, 9])
    ]


def _schema() -> Schema:
    return Schema(id=1, name="Example", encoding="c", data=bytes([4, 5, 6]))


def _channel(schema_id: int = 1) -> Channel:
    if schema_id == 0:
        return Channel(id=1, topic="example", schema_id=0, message_encoding="text", metadata={})
    return Channel(id=1, topic="example", schema_id=1, message_encoding="a",
                   metadata={"foo": "bar"})


def _one_message() -> Message:
    return Message(channel_id=1, sequence=10, log_time=2, publish_time=1, data=bytes([1, 2, 3]))


INPUTS: dict[str, list[McapRecord]] = {
    "NoData": [],
    "OneSchemalessMessage": [_channel(0), _one_message()],
    "OneMessage": [_schema(), _channel(), _one_message()],
    "OneAttachment": [
        Attachment(create_time=1, log_time=2, name="myFile",
                   media_type="application/octet-stream", data=bytes([1, 2, 3]))
    ],
    "OneMetadata": [Metadata(name="myMetadata", metadata={"foo": "bar"})],
    "TenMessages": [_schema(), _channel(), *_ten_messages()],
}


@dataclass(frozen=True)
class Variant:
    """One conformance file: its name, input records and writer features."""

    name: str
    base: str
    features: frozenset[str]

    @property
    def records(self) -> list[McapRecord]:
        return INPUTS[self.base]

    @property
    def messages(self) -> int:
        return sum(isinstance(r, Message) for r in self.records)


def _combinations(features: tuple[str, ...]) -> Iterator[frozenset[str]]:
    if not features:
        yield frozenset()
        return
    for rest in _combinations(features[1:]):
        yield rest
        yield rest | {features[0]}


def _sensible(records: list[McapRecord], f: frozenset[str]) -> bool:
    """generateTestVariants.ts: skip features the data cannot show."""
    kinds = {type(r) for r in records}
    if ("ax" in f and Attachment not in kinds) or ("mdx" in f and Metadata not in kinds):
        return False
    if ("rsh" in f and Schema not in kinds) or ("rch" in f and Channel not in kinds):
        return False
    if not kinds & {Message, Channel, Schema} and f & {"ch", "chx", "mx"}:
        return False
    if "sum" in f and not f & {"chx", "rsh", "rch", "mdx", "ax", "st"}:
        return False
    return not (f & {"chx", "mx"} and "ch" not in f)


def variants() -> list[Variant]:
    """Every conformance variant, as the suite names them (``OneMessage-ch-mx-st``)."""
    found = []
    for base, records in INPUTS.items():
        for features in _combinations(FEATURES):
            if _sensible(records, features):
                name = "-".join([base, *sorted(features)])
                found.append(Variant(name, base, features))
    return found


class _Builder:
    """The file being built: records appended one by one, padded if the variant says so."""

    def __init__(self, pad: bool) -> None:
        self.buffer = bytearray()
        self.pad = pad

    def write(self, record: McapRecord) -> int:
        """Append ``record``; its length in bytes (opcode and length field included)."""
        builder = RecordBuilder()
        record.write(builder)
        data = bytearray(builder.end())
        if self.pad and data[0] not in _UNPADDED:
            data += _PAD
            struct.pack_into("<Q", data, 1, len(data) - 9)
        self.buffer += data
        return len(data)


def generate(variant: Variant) -> bytes:
    """The conformance file of ``variant`` (a port of ``generateFile`` in generate-inputs.ts)."""
    f = variant.features
    out = _Builder("pad" in f)
    out.buffer += MAGIC
    out.write(Header(profile="", library=""))
    chunk = _Builder(pad=False) if "ch" in f else None
    indexes: dict[int, list[tuple[int, int]]] | None = {} if "mx" in f else None
    counts: dict[int, int] = {}
    times: list[int] = []
    metadata_indexes, attachment_indexes, chunk_indexes = [], [], []
    kinds = {Schema: 0, Channel: 0, Attachment: 0, Metadata: 0}
    for record in variant.records:
        if type(record) in kinds:
            kinds[type(record)] += 1
        if isinstance(record, (Schema, Channel)) or isinstance(record, Message):
            if isinstance(record, Channel) and indexes is not None:
                indexes.setdefault(record.id, [])
            if isinstance(record, Message):
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                times.append(record.log_time)
                if indexes is not None and chunk is not None:
                    indexes.setdefault(record.channel_id, []).append(
                        (record.log_time, len(chunk.buffer))
                    )
            (chunk or out).write(record)
        elif isinstance(record, Attachment):
            offset = len(out.buffer)
            length = out.write(record)
            if "ax" in f:
                attachment_indexes.append(AttachmentIndex(
                    offset=offset, length=length, log_time=record.log_time,
                    create_time=record.create_time, data_size=len(record.data),
                    name=record.name, media_type=record.media_type))
        elif isinstance(record, Metadata):
            offset = len(out.buffer)
            length = out.write(record)
            if "mdx" in f:
                metadata_indexes.append(MetadataIndex(offset=offset, length=length,
                                                      name=record.name))
    if chunk is not None:
        raw = bytes(chunk.buffer)
        start, end = (min(times), max(times)) if times else (0, 0)
        chunk_start = len(out.buffer)
        chunk_length = out.write(Chunk(
            message_start_time=start, message_end_time=end, uncompressed_size=len(raw),
            uncompressed_crc=zlib.crc32(raw), compression="", data=raw))
        offsets, index_length = {}, 0
        for channel_id, entries in (indexes or {}).items():
            offsets[channel_id] = len(out.buffer)
            index_length += out.write(MessageIndex(channel_id=channel_id, records=entries))
        if "chx" in f:
            chunk_indexes.append(ChunkIndex(
                message_start_time=start, message_end_time=end, chunk_start_offset=chunk_start,
                chunk_length=chunk_length, message_index_offsets=offsets,
                message_index_length=index_length, compression="", compressed_size=len(raw),
                uncompressed_size=len(raw)))
    out.write(DataEnd(data_section_crc=zlib.crc32(out.buffer)))
    summary_start = len(out.buffer)
    groups: list[tuple[int, int, int]] = []

    def group(opcode: int, records: list[McapRecord]) -> None:
        start = len(out.buffer)
        for record in records:
            out.write(record)
        if len(out.buffer) > start:
            groups.append((opcode, start, len(out.buffer) - start))

    group(Opcode.SCHEMA, [r for r in variant.records if isinstance(r, Schema)]
          if "rsh" in f else [])
    group(Opcode.CHANNEL, [r for r in variant.records if isinstance(r, Channel)]
          if "rch" in f else [])
    group(Opcode.STATISTICS, [Statistics(
        message_count=sum(counts.values()), schema_count=kinds[Schema],
        channel_count=kinds[Channel], attachment_count=kinds[Attachment],
        metadata_count=kinds[Metadata], chunk_count=1 if chunk is not None else 0,
        message_start_time=min(times, default=0), message_end_time=max(times, default=0),
        channel_message_counts=counts)] if "st" in f else [])
    group(Opcode.METADATA_INDEX, metadata_indexes)
    group(Opcode.ATTACHMENT_INDEX, attachment_indexes)
    group(Opcode.CHUNK_INDEX, chunk_indexes)
    has_summary = len(out.buffer) != summary_start
    summary_offset_start = 0
    if "sum" in f:
        summary_offset_start = len(out.buffer)
        for opcode, start, length in groups:
            out.write(SummaryOffset(group_opcode=opcode, group_start=start,
                                    group_length=length))
    footer_start = struct.pack("<BQQQ", Opcode.FOOTER, 20,
                               summary_start if has_summary else 0, summary_offset_start)
    crc = zlib.crc32(footer_start, zlib.crc32(out.buffer[summary_start:]))
    out.write(Footer(summary_start=summary_start if has_summary else 0,
                     summary_offset_start=summary_offset_start, summary_crc=crc))
    out.buffer += MAGIC
    return bytes(out.buffer)


def recorded_crcs(data: bytes) -> tuple[int, int]:
    """(data-section CRC, summary CRC) as written in a file's DataEnd and Footer records."""
    footer = len(data) - len(MAGIC) - 29
    summary_crc = struct.unpack_from("<I", data, footer + 25)[0]
    summary_start = struct.unpack_from("<Q", data, footer + 9)[0]
    data_end = (summary_start or footer) - 13
    assert data[data_end] == Opcode.DATA_END
    return struct.unpack_from("<I", data, data_end + 9)[0], summary_crc


def expected_crcs() -> dict[str, tuple[int, int]]:
    """Variant name -> the CRCs its conformance ``.json`` records."""
    table = json.loads(CRCS.read_text())
    return {name: (int(a), int(b)) for name, (a, b) in table.items()}


def _extract(repo: Path) -> dict[str, list[int]]:
    """Read the CRCs of every conformance ``.json`` under ``repo/tests/conformance/data``."""
    table = {}
    for path in sorted((repo / "tests" / "conformance" / "data").glob("*/*.json")):
        records = json.loads(path.read_text())["records"]
        fields = {r["type"]: dict(r["fields"]) for r in records}
        table[path.stem] = [int(fields["DataEnd"]["data_section_crc"]),
                            int(fields["Footer"]["summary_crc"])]
    return table


if __name__ == "__main__":  # python tests/mcap_conformance.py FOXGLOVE_MCAP_CHECKOUT
    table = _extract(Path(sys.argv[1]))
    rows = [f"{json.dumps(name)}: {json.dumps(crcs)}" for name, crcs in sorted(table.items())]
    CRCS.write_text("{\n" + ",\n".join(rows) + "\n}\n")
    print(f"wrote {CRCS}")
