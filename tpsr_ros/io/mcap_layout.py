"""A bounded check of an MCAP file's record layout, before any reader allocates for it.

MCAP readers (``rosbags``, ``mcap``) read a record by its declared length, and a chunk by
its declared compressed and uncompressed sizes: ``read(length)`` allocates ``length`` bytes
before anything is read. One flipped byte in a length therefore asks for gigabytes (a
record claiming 2**40 bytes is a ``MemoryError``; 2**31 really takes 2 GiB). This module
walks the records that a reader will trust, reading only their 9-byte headers and the
chunk-index fields, and refuses any length that runs past the end of its section or a
chunk whose sizes are impossible or larger than :data:`MAX_CHUNK_BYTES`, with a one-line
``BagError`` naming the file, the offset and the rule.

What is walked is what ``rosbags`` reads: the header record, the footer, the summary
section (chunk indexes included) and, when the summary lists no chunks, every top-level
record of the data section (the reader then scans them all).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

from tpsr_ros.core.errors import BagError

__all__ = ["MAGIC", "MAX_CHUNK_BYTES", "RECORD_HEADER", "check_mcap_layout"]

MAGIC = b"\x89MCAP0\r\n"
MAX_CHUNK_BYTES = 2**28  # rosbag2 writes chunks of about 1 MiB; the mcap CLI 4 MiB
RECORD_HEADER = struct.Struct("<BQ")  # every MCAP record: opcode, body length
_FOOTER = struct.Struct("<BQQQI")  # opcode, length (20), summary start, summary offsets, crc
_CHUNK, _CHUNK_INDEX = 0x06, 0x08


def _fail(path: Path, offset: int, rule: str) -> BagError:
    return BagError(f"{str(path)!r} is damaged: the record at offset {offset} {rule}")


def _records(handle: BinaryIO, path: Path, start: int, end: int) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of every record in [start, end), each within the section."""
    found = []
    offset = start
    while offset < end:
        handle.seek(offset)
        head = handle.read(RECORD_HEADER.size)
        if len(head) < RECORD_HEADER.size or offset + RECORD_HEADER.size > end:
            raise _fail(path, offset, f"is cut short at the section end ({end})")
        opcode, length = RECORD_HEADER.unpack(head)
        if length > end - offset - RECORD_HEADER.size:
            raise _fail(
                path, offset, f"claims {length} bytes; only {end - offset - 9} remain before {end}"
            )
        found.append((offset, opcode, length))
        offset += RECORD_HEADER.size + length
    return found


def _check_sizes(path: Path, offset: int, compressed: int, uncompressed: int, room: int) -> None:
    if compressed > room:
        raise _fail(path, offset, f"holds a chunk of {compressed} bytes in {room}")
    if uncompressed > MAX_CHUNK_BYTES:
        raise _fail(
            path, offset, f"declares a chunk of {uncompressed} bytes, more than {MAX_CHUNK_BYTES}"
        )


def _check_chunk(handle: BinaryIO, path: Path, offset: int, length: int) -> None:
    """Check that a chunk record's declared sizes fit its record and the bound."""
    handle.seek(offset + RECORD_HEADER.size)
    body = handle.read(min(length, 32 + 2**16))
    if len(body) < 32:
        raise _fail(path, offset, "is too short for a chunk")
    uncompressed = struct.unpack_from("<Q", body, 16)[0]
    (name_length,) = struct.unpack_from("<I", body, 28)
    if 40 + name_length > min(length, len(body)):
        raise _fail(path, offset, f"names a compression of {name_length} bytes")
    (compressed,) = struct.unpack_from("<Q", body, 32 + name_length)
    _check_sizes(path, offset, compressed, uncompressed, length - 40 - name_length)


def _check_chunk_index(handle: BinaryIO, path: Path, offset: int, length: int,
                       data_end: int) -> None:
    """Check that a chunk index points inside the data section at a bounded chunk."""
    handle.seek(offset + RECORD_HEADER.size)
    body = handle.read(length)
    try:
        _, _, chunk_start, chunk_length = struct.unpack_from("<QQQQ", body, 0)
        (map_length,) = struct.unpack_from("<I", body, 32)
        at = 36 + map_length
        (_, name_length) = struct.unpack_from("<QI", body, at)
        at += 12 + name_length
        compressed, uncompressed = struct.unpack_from("<QQ", body, at)
    except struct.error:
        raise _fail(path, offset, "is a chunk index cut short") from None
    if chunk_start + chunk_length > data_end or chunk_length < RECORD_HEADER.size:
        raise _fail(
            path, offset, f"indexes a chunk at {chunk_start} of {chunk_length} bytes, "
            f"outside the data section (which ends at {data_end})"
        )
    _check_sizes(path, offset, compressed, uncompressed, chunk_length)


def check_mcap_layout(path: Path) -> None:
    """Refuse an MCAP file whose record lengths or chunk sizes a reader cannot trust."""
    path = Path(path)
    try:
        handle = path.open("rb")
    except OSError as exc:
        raise BagError(f"cannot read {str(path)!r}: {exc.strerror}") from None
    with handle:
        size = handle.seek(0, 2)
        handle.seek(0)
        if handle.read(len(MAGIC)) != MAGIC:
            raise BagError(f"{str(path)!r} is not an MCAP file (no MCAP magic)")
        footer_start = size - len(MAGIC) - _FOOTER.size
        if footer_start < len(MAGIC):
            raise BagError(f"{str(path)!r} is damaged: {size} bytes are too few for MCAP")
        handle.seek(footer_start)
        opcode, length, summary_start, _, _ = _FOOTER.unpack(handle.read(_FOOTER.size))
        if opcode != 0x02 or length != 20 or handle.read(len(MAGIC)) != MAGIC:
            raise BagError(
                f"{str(path)!r} has no MCAP footer: the recording did not finish "
                f"(run `python -m tpsr_ros.bag_recover` on its bag)"
            )
        if summary_start and not len(MAGIC) < summary_start <= footer_start:
            raise BagError(f"{str(path)!r} is damaged: summary offset {summary_start} is outside "
                           f"the file")
        data_end = summary_start or footer_start
        chunk_indexes = 0
        if summary_start:
            for offset, opcode, length in _records(handle, path, summary_start, footer_start):
                if opcode == _CHUNK_INDEX:
                    _check_chunk_index(handle, path, offset, length, data_end)
                    chunk_indexes += 1
        if chunk_indexes:
            _first_record(handle, path, data_end)
            return
        for offset, opcode, length in _records(handle, path, len(MAGIC), data_end):
            if opcode == _CHUNK:
                _check_chunk(handle, path, offset, length)


def _first_record(handle: BinaryIO, path: Path, data_end: int) -> None:
    """Check that the header record (the first after the magic) fits the data section."""
    handle.seek(len(MAGIC))
    head = handle.read(RECORD_HEADER.size)
    if len(head) < RECORD_HEADER.size:
        raise _fail(path, len(MAGIC), "is cut short")
    _, length = RECORD_HEADER.unpack(head)
    if length > data_end - len(MAGIC) - RECORD_HEADER.size:
        raise _fail(path, len(MAGIC), f"claims {length} bytes, past the data section")
