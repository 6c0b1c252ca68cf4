"""The mutators of ``tests/fuzz_cli.py``: hostile variants of YAML, ``.npz`` archives and MCAP.

Each takes the bytes of a valid file and a seeded generator and returns bytes a user
could hand the commands and nodes: values of the wrong type or size, aliases and deep
nesting in YAML, members changed or swapped or huge in archives, records and chunks cut,
corrupted or re-compressed in MCAP.
"""

from __future__ import annotations

import io
import json
import re
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
from test_fuzz import mutate  # the byte-level mutator the CI fuzz suite uses

HOSTILE_SCALARS = (
    "-1", "0", "1e308", "-1e308", ".nan", ".inf", "-.inf", "0x7fffffffffffffff",
    "18446744073709551616", "-9223372036854775809", "9" * 5001, "1:00", "1.5", "true", "",
    "null", "~", "[]", "{}", "[1, 2]", "[1.0, 2.5, 1e400]", "{a: 1}", "[[1], [2]]",
    "[" * 3000 + "]" * 3000, "{a: " * 200 + "1" + "}" * 200, "*x", "&a [1]", "'quoted'",
    '"\\xff\\u0000"', "x" * 100_000, "!!python/object/apply:os.system ['true']",
    "!!binary aGVsbG8=", "[true, 1, x]", "1_000", "0o17", "017", "-0", "1e-400",
    "/dev/zero", "/proc/self/mem", "..", "/", "\x00", "a\nb: c",
)
HOSTILE_JSON = (
    -1, 0, 2**64, 10**400, 1e308, -1e308, float("nan"), float("inf"), "", "x" * 10_000, None,
    True, [], {}, [1, 2], {"a": 1}, [[1.0] * 3] * 3, "../../etc/passwd",
)
LAUGHS = "\n".join(
    ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    + [f"{chr(98 + i)}: &{chr(98 + i)} [{','.join(['*' + chr(97 + i)] * 9)}]" for i in range(8)]
)


# -- mutators -------------------------------------------------------------------------------


def pick(rng: np.random.Generator, items):
    return items[int(rng.integers(len(items)))]


def mutate_yaml(data: bytes, rng: np.random.Generator) -> bytes:
    """Replace a value, rename a key, inject aliases or nesting, or mutate the bytes."""
    kind = int(rng.integers(6))
    lines = data.decode("utf-8", "replace").split("\n")
    valued = [i for i, line in enumerate(lines) if re.match(r"^\s*[-\w./]+:\s*\S", line)]
    if kind <= 1 and valued:
        i = pick(rng, valued)
        key = lines[i].split(":", 1)[0]
        value = pick(rng, HOSTILE_SCALARS)
        lines[i] = f"{key}: {value}"
        out = "\n".join(lines).encode("utf-8", "surrogateescape")
        return out.replace(b"\\xff", b"\xff") if rng.integers(4) == 0 else out
    if kind == 2 and valued:
        i = pick(rng, valued)
        key, rest = lines[i].split(":", 1)
        indent = key[: len(key) - len(key.lstrip())]
        new_key = pick(rng, ("x", "<<", "? ", '"', "a" * 300, "1"))
        lines[i] = f"{indent}{new_key}:{rest}"
        return "\n".join(lines).encode()
    if kind == 3:
        return (LAUGHS + "\n").encode() + data
    if kind == 4 and valued:
        i = pick(rng, valued)
        lines.insert(i + 1, lines[i])  # a duplicated key
        return "\n".join(lines).encode()
    return mutate(data, rng)


def _npz_members(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _npz_bytes(members: dict[str, bytes], raw: dict[str, tuple[bytes, int, int]]) -> bytes:
    """A zip of ``members`` (deflated) plus ``raw`` members given as (deflated, crc, size)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, body in members.items():
            archive.writestr(name, body)
    if not raw:
        return buffer.getvalue()
    # append raw deflated members by hand (zipfile cannot take pre-compressed bodies)
    entries = _zip_entries(buffer.getvalue())
    body = bytearray(buffer.getvalue()[: entries["cd_offset"]])
    central = bytearray(buffer.getvalue()[entries["cd_offset"] : entries["eocd_offset"]])
    count = entries["count"]
    for name, (deflated, crc, size) in raw.items():
        encoded = name.encode()
        offset = len(body)
        zip64 = size >= 0xFFFFFFFF
        extra = struct.pack("<HHQQ", 1, 16, size, len(deflated)) if zip64 else b""
        sizes = (0xFFFFFFFF, 0xFFFFFFFF) if zip64 else (len(deflated), size)
        body += struct.pack("<IHHHHHIIIHH", 0x04034B50, 45, 0, 8, 0, 0, crc, *sizes,
                            len(encoded), len(extra)) + encoded + extra + deflated
        cextra = struct.pack("<HHQQ", 1, 16, size, len(deflated)) if zip64 else b""
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, 8, 0, 0, crc,
                               *sizes, len(encoded), len(cextra), 0, 0, 0, 0, offset)
        central += encoded + cextra
        count += 1
    eocd = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, count, count, len(central), len(body), 0)
    return bytes(body + central + eocd)


def _zip_entries(data: bytes) -> dict[str, int]:
    eocd = data.rfind(b"PK\x05\x06")
    count, _, offset = struct.unpack_from("<HII", data, eocd + 10)
    return {"eocd_offset": eocd, "count": count, "cd_offset": offset}


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def _npy_with_header(body: bytes, header: dict) -> bytes:
    """``body``'s data after a rewritten ``.npy`` header."""
    version = np.lib.format.read_magic(io.BytesIO(body))
    stream = io.BytesIO(body)
    np.lib.format.read_magic(stream)
    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
            else np.lib.format.read_array_header_2_0)
    read(stream)
    data = body[stream.tell():]
    out = io.BytesIO()
    np.lib.format.write_array_header_2_0(out, header)
    return out.getvalue() + data


def _json_paths(value, path=()):
    yield path
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _json_paths(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value[:8]):
            yield from _json_paths(item, (*path, index))


def _json_set(value, path, new):
    if not path:
        return new
    holder = value
    for key in path[:-1]:
        holder = holder[key]
    if new is _DELETE and isinstance(holder, dict):
        del holder[path[-1]]
    elif new is not _DELETE:
        holder[path[-1]] = new
    return value


_DELETE = object()


def mutate_npz(data: bytes, rng: np.random.Generator, bomb: Path) -> bytes:
    """A structural change of a model or policy archive, or a byte-level one."""
    kind = int(rng.integers(7))
    if kind == 0:
        return mutate(data, rng)
    members = _npz_members(data)
    arrays = [name for name in members if name != "metadata.npy"]
    raw: dict[str, tuple[bytes, int, int]] = {}
    if kind in (1, 2):  # the JSON metadata
        meta = json.loads(str(np.load(io.BytesIO(members["metadata.npy"]), allow_pickle=False)))
        paths = list(_json_paths(meta))
        path = pick(rng, paths[1:] or paths)
        if kind == 1:
            new = pick(rng, (*HOSTILE_JSON, _DELETE))
        else:
            depth = int(rng.choice([70, 1000, 20000]))
            new = json.loads("[" * depth + "]" * depth) if depth < 900 else _DELETE
            if new is _DELETE:  # too deep for json.loads here: splice the text in
                text = json.dumps(_json_set(meta, path, "@@DEEP@@"))
                text = text.replace('"@@DEEP@@"', "[" * depth + "]" * depth)
                members["metadata.npy"] = _npy(np.array(text))
                return _npz_bytes(members, raw)
        meta = _json_set(meta, path, new)
        members["metadata.npy"] = _npy(np.array(json.dumps(meta)))
    elif kind == 3 and arrays:  # a lying .npy header
        name = pick(rng, arrays)
        array = np.load(io.BytesIO(members[name]), allow_pickle=False)
        shape = list(array.shape)
        choice = int(rng.integers(5))
        if choice == 0:
            shape = [2**40]
        elif choice == 1 and shape:
            shape[int(rng.integers(len(shape)))] = int(rng.choice([0, 2**31, 2**62, 1]))
        elif choice == 2:
            shape = [*shape[::-1], 1]
        descr = pick(rng, ("<f8", "<f4", ">f8", "<c16", "|O", "<U8", "|b1", "<i8", "<f2",
                            "|V8", "<M8[s]")) if choice == 3 else array.dtype.str
        header = {"descr": descr, "fortran_order": bool(choice == 4), "shape": tuple(shape)}
        members[name] = _npy_with_header(members[name], header)
    elif kind == 4 and arrays:  # well-formed arrays with hostile contents or shapes
        name = pick(rng, arrays)
        array = np.load(io.BytesIO(members[name]), allow_pickle=False)
        choice = int(rng.integers(4))
        if choice == 0 and array.size:
            flat = array.astype(np.float64).ravel()
            flat[rng.integers(flat.size, size=max(1, flat.size // 10))] = pick(
                rng, (np.nan, np.inf, -np.inf, 1e308, 0.0))
            array = flat.reshape(array.shape)
        elif choice == 1:
            array = np.zeros(tuple(int(s) + int(rng.integers(1, 3)) for s in array.shape))
        elif choice == 2:
            array = array.astype(pick(rng, (np.int8, np.complex128, np.float16, np.bool_)))
        else:
            array = array.reshape(-1)
        members[name] = _npy(array)
    elif kind == 5 and arrays:  # a compression bomb in place of an array
        name = pick(rng, arrays)
        del members[name]
        meta = json.loads(bomb.with_suffix(".json").read_text())
        raw[name] = (bomb.read_bytes(), meta["crc"], meta["size"])
    else:  # duplicated, missing or foreign members
        choice = int(rng.integers(3))
        if choice == 0 and arrays:
            del members[pick(rng, arrays)]
        elif choice == 1:
            members["../evil.npy"] = _npy(np.arange(3.0))
        else:
            members[f"extra{int(rng.integers(100))}.npy"] = _npy(np.zeros((300, 300)))
    return _npz_bytes(members, raw)


_RECORD = struct.Struct("<BQ")


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level MCAP records, as far as they parse."""
    out, offset = [], 8
    while offset + 9 <= len(data):
        opcode, length = _RECORD.unpack_from(data, offset)
        if offset + 9 + length > len(data):
            break
        out.append((offset, opcode, length))
        offset += 9 + length
    return out


def _chunk_parts(body: bytes) -> tuple[int, int, int, int, str, bytes]:
    start, end, size, crc = struct.unpack_from("<QQQI", body, 0)
    (n,) = struct.unpack_from("<I", body, 28)
    compression = body[32 : 32 + n].decode()
    (m,) = struct.unpack_from("<Q", body, 32 + n)
    return start, end, size, crc, compression, body[40 + n : 40 + n + m]


def _compress(compression: str, raw: bytes) -> bytes:
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdCompressor().compress(raw)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.compress(raw)
    return raw


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    return data


def _chunk(start: int, end: int, compression: str, raw: bytes, *, size: int | None = None,
           crc: int | None = None) -> bytes:
    packed = _compress(compression, raw)
    name = compression.encode()
    body = (struct.pack("<QQQI", start, end, len(raw) if size is None else size,
                        zlib.crc32(raw) if crc is None else crc)
            + struct.pack("<I", len(name)) + name + struct.pack("<Q", len(packed)) + packed)
    return _RECORD.pack(0x06, len(body)) + body


def mutate_mcap(data: bytes, rng: np.random.Generator) -> bytes:
    """A byte-level change, a record-level one, or a change inside a chunk behind a valid CRC."""
    records = _records(data)
    kind = int(rng.integers(4))
    if kind == 0 or not records:
        return mutate(data, rng)
    offset, _, length = pick(rng, records)
    out = bytearray(data)
    if kind == 1:  # the record's opcode or length
        if rng.integers(2):
            out[offset] = int(rng.integers(256))
        else:
            new = int(rng.choice([0, 1, length - 1, length + 1, 2**31, 2**40, 2**64 - 1]))
            out[offset + 1 : offset + 9] = struct.pack("<Q", new % 2**64)
        return bytes(out)
    chunks = [r for r in records if r[1] == 0x06]
    if not chunks:
        return mutate(data, rng)
    offset, _, length = pick(rng, chunks)
    body = data[offset + 9 : offset + 9 + length]
    start, end, size, _, compression, packed = _chunk_parts(body)
    raw = _decompress(compression, packed, size)
    if kind == 2:  # the chunk's own fields
        choice = int(rng.integers(4))
        if choice == 0:
            new = _chunk(start, end, compression, raw, size=int(rng.choice([0, 2**40, size - 1])))
        elif choice == 1:
            new = _chunk(start, end, compression, raw, crc=int(rng.integers(2**32)))
        elif choice == 2:
            new = _chunk(start, end, pick(rng, ("", "lz4", "bogus", "zstd")), raw)
        else:
            new = _chunk(int(rng.integers(2**63)), int(rng.integers(2**63)), compression, raw)
    else:  # the records inside, with a CRC that matches the damage
        new = _chunk(start, end, compression, mutate(raw, rng))
    return data[:offset] + new + data[offset + 9 + length :]


def rewrite_messages(source: Path, target: Path, rng: np.random.Generator) -> None:
    """A valid MCAP file holding ``source``'s messages, a few of them hostile."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with source.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        messages = [(m.channel_id, m.log_time, m.publish_time, m.sequence, m.data)
                    for _, _, m in reader.iter_messages(log_time_order=False)]
    picked = set(rng.integers(len(messages), size=int(rng.integers(1, 6))).tolist())
    with target.open("wb") as handle:
        writer = Writer(handle, compression=CompressionType.ZSTD, enable_crcs=True)
        writer.start(profile="ros2", library="fuzz")
        schema_ids = {s.id: writer.register_schema(s.name, s.encoding, s.data)
                      for s in summary.schemas.values()}
        channel_ids = {c.id: writer.register_channel(c.topic, c.message_encoding,
                                                     schema_ids.get(c.schema_id, 0),
                                                     dict(c.metadata))
                       for c in summary.channels.values()}
        for index, (channel, log_time, publish_time, sequence, payload) in enumerate(messages):
            if index in picked:
                choice = int(rng.integers(3))
                if choice == 0:
                    payload = mutate(payload, rng)
                elif choice == 1:
                    log_time = int(rng.choice([0, 2**63 - 1, max(0, log_time - 10**12),
                                               int(rng.integers(2**63))]))
                else:
                    at = int(rng.integers(4, max(5, len(payload) - 4)))
                    payload = (payload[:at]
                               + struct.pack("<I", int(rng.choice([0, 2**31 - 1, 2**32 - 1])))
                               + payload[at + 4 :])
            writer.add_message(channel_ids[channel], log_time, payload, publish_time, sequence)
        writer.finish()


