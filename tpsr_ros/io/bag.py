"""rosbag2 MCAP bags: the one module the generator, recorder, player and learner share.

A bag is a rosbag2 directory (``metadata.yaml`` + ``<name>.mcap``, storage ``mcap``,
serialisation ``cdr``), written with the ``mcap`` library (zstd chunks with CRCs) and
read with ``rosbags``; ``ros2 bag``, ``rosbags`` and ``mcap`` all read it. Reading is
bounded and checked: ``metadata.yaml`` through :mod:`tpsr_ros.io.safe_yaml`, damaged MCAP
bytes and chunk CRC mismatches as one-line ``BagError`` reports, and a bag that yields fewer
messages than its metadata lists is refused.

Writing never clobbers: an existing path is refused, an unwritable directory is named,
and a writer that fails or is interrupted inside its ``with`` block removes what it
wrote. ``BagWriter.flush`` pushes every complete message to the operating system so a
recorder that is killed hard loses at most what arrived since its last flush.
"""

from __future__ import annotations

import importlib
import os
import shutil
import struct
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.metadata import dump_qos_v9

from tpsr_ros.core.errors import BagError, MessageError, one_line
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.mcap_layout import check_mcap_layout
from tpsr_ros.io.messages import (
    deserialize,
    jazzy_typestore,
    message_definition,
    serialize,
)
from tpsr_ros.io.safe_yaml import YamlInputError, load_yaml

__all__ = [
    "BagFile",
    "BagMessage",
    "BagReader",
    "BagWriter",
    "check_bag_path_free",
    "read_bag_metadata",
    "rosbag2_metadata",
]

MAX_METADATA_BYTES = 16 * 2**20


def _zstd_errors() -> tuple[type[Exception], ...]:
    """The error type of the zstd module rosbags decompresses with (stdlib or backport)."""
    for name in ("compression.zstd", "backports.zstd"):
        try:
            return (importlib.import_module(name).ZstdError,)
        except (ImportError, AttributeError):
            continue
    return ()


_DAMAGE = (
    ValueError,
    RuntimeError,
    OverflowError,
    IndexError,
    KeyError,
    EOFError,
    MemoryError,
    struct.error,
    *_zstd_errors(),
)
"""What a corrupt MCAP file makes rosbags' reader raise besides ``ReaderError``: a
decompressor's error (zstd's ``ZstdError``, lz4's ``RuntimeError``), impossible lengths
and offsets (``OverflowError``, ``struct.error``, ``MemoryError`` from an allocation that
was refused before it happened). A damaged bag is reported, never a traceback."""


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {one_line(exc, 120)}"


def check_bag_path_free(path: Path) -> Path:
    """Refuse an existing bag path or an unwritable parent directory, before any work."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        raise BagError(f"output path {str(path)!r} already exists; refusing to overwrite it")
    parent = path.resolve().parent
    if not parent.is_dir():
        raise BagError(f"output directory {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise BagError(f"output directory {str(parent)!r} is not writable")
    return path


@dataclass
class _Topic:
    """A declared topic: its MCAP channel and what ``metadata.yaml`` says of it."""

    channel_id: int
    msgtype: str
    qos: str
    rihs01: str
    count: int = 0


@dataclass(frozen=True)
class BagFile:
    """One ``.mcap`` file of a bag as ``metadata.yaml`` lists it: name, times, count."""

    name: str
    start_ns: int  # first log time (0 without messages)
    end_ns: int  # last log time
    message_count: int


def rosbag2_metadata(
    files: Sequence[BagFile], topics: Sequence[dict[str, Any]],
    custom_data: dict[str, str] | None = None,
) -> str:
    """``metadata.yaml`` (rosbag2 version 9) for the MCAP ``files`` of one bag, in order.

    ``topics`` are ``{"name", "type", "serialization_format", "offered_qos_profiles",
    "type_description_hash", "message_count"}`` over all files.
    """
    filled = [f for f in files if f.message_count]
    start = min((f.start_ns for f in filled), default=0)
    duration = max((f.end_ns for f in filled), default=0) - start if filled else 0
    total = sum(int(t["message_count"]) for t in topics)
    info = {
        "version": 9,
        "storage_identifier": "mcap",
        "relative_file_paths": [f.name for f in files],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": total,
        "topics_with_message_count": [
            {
                "topic_metadata": {k: v for k, v in t.items() if k != "message_count"},
                "message_count": int(t["message_count"]),
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [
            {
                "path": f.name,
                "starting_time": {"nanoseconds_since_epoch": f.start_ns},
                "duration": {"nanoseconds": max(0, f.end_ns - f.start_ns)},
                "message_count": f.message_count,
            }
            for f in files
        ],
        "custom_data": dict(custom_data) if custom_data else None,
        "ros_distro": "jazzy",
    }
    return yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)


class BagWriter:
    """Write serialised ROS 2 messages into a new rosbag2 MCAP bag.

    Use as a context manager. Topics are declared once with :meth:`add_topic`; messages
    are written as CDR bytes (:meth:`write`, what a recorder receives) or as message
    objects (:meth:`write_message`, serialised here).

    The file is written by the ``mcap`` library, as ROS 2's own recorder writes it: the
    ``ros2`` profile, a ``ros2msg`` schema per type, the offered QoS in each channel's
    metadata, zstd chunks of about 1 MiB carrying a CRC of their content (so a flipped
    bit is detected when read, not passed on silently), chunk and message indexes, and a
    summary. ``metadata.yaml`` is written on :meth:`close`.
    """

    def __init__(self, path: Path | str, *, compress: bool = True) -> None:
        self.path = check_bag_path_free(Path(path))
        self._compress = compress
        self._handle: Any = None
        self._writer: McapWriter | None = None
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._custom_data: dict[str, str] = {}
        self._times = (2**63 - 1, 0)
        self.message_count = 0

    @property
    def _file(self) -> Path:
        return self.path / f"{self.path.name}.mcap"

    def open(self) -> BagWriter:
        """Create the bag directory and MCAP file."""
        try:
            self.path.mkdir()
            self._handle = self._file.open("wb")
        except OSError as exc:
            raise BagError(f"cannot create bag {str(self.path)!r}: {exc.strerror}") from None
        compression = CompressionType.ZSTD if self._compress else CompressionType.NONE
        self._writer = McapWriter(self._handle, compression=compression, enable_crcs=True)
        self._writer.start(profile="ros2", library=f"tpsr_ros {_version()}")
        return self

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _require_open(self) -> McapWriter:
        if self._writer is None:
            raise BagError(f"bag {str(self.path)!r} is not open")
        return self._writer

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """Declare ``topic`` with ROS type ``msgtype``; a clashing redeclaration is refused."""
        writer = self._require_open()
        if topic in self._topics:
            if self._topics[topic].msgtype != msgtype:
                raise BagError(
                    f"topic {topic!r} already has type {self._topics[topic].msgtype}, "
                    f"not {msgtype}"
                )
            return
        try:
            msgdef = message_definition(msgtype)
        except MessageError as exc:
            raise BagError(f"cannot record {topic!r}: {exc}") from None
        rihs01 = jazzy_typestore().hash_rihs01(msgtype)
        if msgtype not in self._schemas:
            self._schemas[msgtype] = writer.register_schema(msgtype, "ros2msg", msgdef.encode())
        offered = _dump_qos(list(qos))
        channel = writer.register_channel(
            topic, "cdr", self._schemas[msgtype], {"offered_qos_profiles": offered}
        )
        self._topics[topic] = _Topic(channel, msgtype, offered, rihs01)

    def set_custom_data(self, key: str, value: str) -> None:
        """Store a string in ``metadata.yaml``'s ``custom_data`` (e.g. generator settings)."""
        self._custom_data[str(key)] = str(value)

    def has_topic(self, topic: str) -> bool:
        """Whether ``topic`` was declared."""
        return topic in self._topics

    def write(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> None:
        """Append CDR bytes on a declared topic with log time ``stamp_ns``."""
        writer = self._require_open()
        try:
            declared = self._topics[topic]
        except KeyError:
            raise BagError(f"topic {topic!r} was not declared with add_topic") from None
        stamp = int(stamp_ns)
        writer.add_message(declared.channel_id, stamp, bytes(data), stamp, declared.count)
        declared.count += 1
        self.message_count += 1
        self._times = (min(self._times[0], stamp), max(self._times[1], stamp))

    def write_message(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialise ``msg`` with the topic's declared type and append it."""
        if topic not in self._topics:
            raise BagError(f"topic {topic!r} was not declared with add_topic")
        self.write(topic, stamp_ns, serialize(msg, self._topics[topic].msgtype))

    def flush(self) -> None:
        """Close the pending MCAP chunk and hand everything written so far to the OS.

        After a hard kill the ``.mcap`` then holds every message up to this call; see
        ``tpsr_ros.bag_recover`` for reading such a bag.
        """
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        """Finish the MCAP summary and write ``metadata.yaml``."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        writer.finish()
        self._handle.close()
        topics = [
            {
                "name": name,
                "type": t.msgtype,
                "serialization_format": "cdr",
                "offered_qos_profiles": t.qos,
                "type_description_hash": t.rihs01,
                "message_count": t.count,
            }
            for name, t in self._topics.items()
        ]
        times = self._times if self.message_count else (0, 0)
        file = BagFile(self._file.name, times[0], times[1], self.message_count)
        text = rosbag2_metadata([file], topics, self._custom_data)
        with atomic_file(self.path / "metadata.yaml", "w", sync=False) as handle:
            handle.write(text)

    def abort(self) -> None:
        """Discard the bag: close files and remove the directory this writer created."""
        if self._writer is not None:
            self._writer = None
            try:
                self._handle.close()
            finally:
                shutil.rmtree(self.path, ignore_errors=True)


def _dump_qos(profiles: list[Qos]) -> str:
    """Offered QoS profiles as rosbag2 (version 9) stores them: a YAML string."""
    dumped = dump_qos_v9(profiles)
    if isinstance(dumped, str):
        return dumped
    return yaml.safe_dump(dumped, default_flow_style=False, sort_keys=False).strip()


def _version() -> str:
    from tpsr_ros import __version__

    return str(__version__)


@dataclass(frozen=True)
class BagMessage:
    """One message read from a bag: topic, ROS type, log time and CDR bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes

    def decode(self) -> Any:
        """Deserialise the CDR bytes into a message object."""
        return deserialize(self.data, self.msgtype)


def read_bag_metadata(path: Path) -> dict[str, Any]:
    """The validated ``rosbag2_bagfile_information`` of the bag directory ``path``.

    ``metadata.yaml`` is read bounded (:mod:`tpsr_ros.io.safe_yaml`: UTF-8, 16 MiB, no
    aliases, shallow nesting); ``custom_data`` must be a mapping and
    ``relative_file_paths`` a list of names.
    """
    meta_path = path / "metadata.yaml"
    if not path.is_dir():
        raise BagError(f"{str(path)!r} is not a rosbag2 directory")
    if not meta_path.is_file():
        raise BagError(
            f"{str(path)!r} has no metadata.yaml; if a recorder was killed, "
            f"run `python -m tpsr_ros.bag_recover {path}` first"
        )
    try:
        with meta_path.open("rb") as handle:
            data = handle.read(MAX_METADATA_BYTES + 1)
        what = f"{str(meta_path)!r} is not rosbag2 metadata"
        meta = load_yaml(data, what, max_bytes=MAX_METADATA_BYTES)
    except OSError as exc:
        raise BagError(f"cannot read {str(meta_path)!r}: {exc.strerror}") from None
    except YamlInputError as exc:
        raise BagError(str(exc)) from None
    info = meta.get("rosbag2_bagfile_information") if isinstance(meta, dict) else None
    if not isinstance(info, dict):
        raise BagError(f"{str(meta_path)!r} is not rosbag2 metadata")
    custom = info.get("custom_data")
    if custom is not None and not isinstance(custom, dict):
        raise BagError(f"{str(meta_path)!r}: custom_data is not a mapping")
    files = info.get("relative_file_paths", [])
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        raise BagError(f"{str(meta_path)!r}: relative_file_paths is not a list of file names")
    _check_counts(meta_path, info)
    return info


def _count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _nested(info: dict[str, Any], key: str, field: str) -> Any:
    """``info[key][field]`` (0 when absent, None when ``info[key]`` is not a mapping)."""
    outer = info.get(key) or {}
    return outer.get(field, 0) if isinstance(outer, dict) else None


def _check_counts(meta_path: Path, info: dict[str, Any]) -> None:
    """Refuse metadata whose counts, times and topic entries are not what rosbag2 writes."""
    where = f"{str(meta_path)!r}"
    numbers = {
        "message_count": info.get("message_count", 0),
        "duration.nanoseconds": _nested(info, "duration", "nanoseconds"),
        "starting_time.nanoseconds_since_epoch": _nested(
            info, "starting_time", "nanoseconds_since_epoch"
        ),
    }
    for name, value in numbers.items():
        if not _count(value):
            raise BagError(f"{where}: {name} is not a non-negative integer")
    topics = info.get("topics_with_message_count", [])
    if not isinstance(topics, list):
        raise BagError(f"{where}: topics_with_message_count is not a list")
    for entry in topics:
        topic = entry.get("topic_metadata") if isinstance(entry, dict) else None
        if not isinstance(topic, dict) or not all(
            isinstance(topic.get(key), str) for key in ("name", "type")
        ):
            raise BagError(f"{where}: a topic entry lacks its name or type")
        if not _count(entry.get("message_count", 0)):
            raise BagError(f"{where}: topic {topic['name'][:80]!r} has a bad message_count")


def _bag_file(bag: Path, name: str) -> Path:
    """Return the bag's file ``name`` (from ``relative_file_paths``); it must lie inside."""
    file = bag / name
    if Path(name).is_absolute() or ".." in Path(name).parts or not file.is_file():
        raise BagError(
            f"{str(bag / 'metadata.yaml')!r} lists {name[:200]!r}, which is not a file "
            "inside the bag"
        )
    return file


class BagReader:
    """Read a rosbag2 MCAP bag; anything else is refused with a ``BagError``."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        info = read_bag_metadata(self.path)
        self._custom_data = {str(k): str(v) for k, v in (info.get("custom_data") or {}).items()}
        self._files = tuple(info.get("relative_file_paths", []))
        storage = info.get("storage_identifier")
        if storage != "mcap":
            raise BagError(f"bag {str(self.path)!r} uses storage {storage!r}, not mcap")
        for name in info.get("relative_file_paths", []):
            check_mcap_layout(_bag_file(self.path, name))
        self._reader = Reader(self.path)
        try:
            self._reader.open()
        except (ReaderError, OSError) as exc:
            raise BagError(f"cannot open bag {str(self.path)!r}: {one_line(exc)}") from None
        except (*_DAMAGE, TypeError, AttributeError) as exc:  # metadata rosbags did not expect
            damage = _describe(exc)
            raise BagError(f"cannot open bag {str(self.path)!r}: damaged ({damage})") from None
        for connection in self._reader.connections:  # rosbags' YAML 1.2 view of metadata.yaml
            if not (isinstance(connection.topic, str) and isinstance(connection.msgtype, str)):
                self._reader.close()
                raise BagError(
                    f"{str(self.path / 'metadata.yaml')!r}: topic {str(connection.topic)[:80]!r}"
                    f" has a name or type that is not text ({str(connection.msgtype)[:80]!r})"
                )

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying files."""
        self._reader.close()

    @property
    def topics(self) -> dict[str, str]:
        """Topic name to ROS type."""
        return {c.topic: c.msgtype for c in self._reader.connections}

    @property
    def message_counts(self) -> dict[str, int]:
        """Topic name to number of messages."""
        counts: dict[str, int] = {}
        for c in self._reader.connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        return counts

    @property
    def topics_with_messages(self) -> dict[str, str]:
        """Topic name to ROS type, for the topics that have at least one message."""
        counts = self.message_counts
        return {t: ty for t, ty in self.topics.items() if counts.get(t, 0) > 0}

    @property
    def start_time_ns(self) -> int:
        """Log time of the first message."""
        return int(self._reader.start_time)

    @property
    def end_time_ns(self) -> int:
        """Log time just after the last message."""
        return int(self._reader.end_time)

    @property
    def files(self) -> tuple[str, ...]:
        """The bag's MCAP files as ``metadata.yaml`` lists them (relative to the bag)."""
        return self._files

    @property
    def custom_data(self) -> dict[str, str]:
        """The ``custom_data`` strings of ``metadata.yaml`` (empty when absent)."""
        return dict(self._custom_data)

    @property
    def qos_profiles(self) -> dict[str, list[Qos]]:
        """Offered QoS profiles recorded per topic."""
        return {
            c.topic: list(getattr(c.ext, "offered_qos_profiles", []))
            for c in self._reader.connections
        }

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Yield messages in log-time order, optionally only on ``topics``.

        Read to the end, the messages must number what ``metadata.yaml`` lists for those
        topics; otherwise a ``BagError`` says how many were missing.
        """
        for conn, log_time, data in self._checked(topics):
            yield BagMessage(conn.topic, conn.msgtype, log_time, data)

    def raw_messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log_time_ns, cdr_bytes)`` as :meth:`messages` reads them, with no object
        per message: for readers that decode a few known types themselves.

        The type of a topic is :attr:`topics`'s: a topic whose connections have different
        types is refused (its bytes could not be decoded as one type).
        """
        wanted = None if topics is None else set(topics)
        types: dict[str, str] = {}
        for conn in self._reader.connections:
            if wanted is not None and conn.topic not in wanted:
                continue
            if types.setdefault(conn.topic, conn.msgtype) != conn.msgtype:
                raise BagError(
                    f"bag {str(self.path)!r}: topic {conn.topic!r} has messages of two types, "
                    f"{types[conn.topic]} and {conn.msgtype}"
                )
        for conn, log_time, data in self._checked(topics):
            yield conn.topic, log_time, data

    def _checked(self, topics: Iterable[str] | None) -> Iterator[tuple[Any, int, bytes]]:
        """rosbags' ``(connection, log time, bytes)``; damage and lost messages as BagError."""
        wanted = None if topics is None else set(topics)
        connections = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        if wanted is not None and not connections:
            return
        listed = sum(c.msgcount for c in connections)
        read = 0
        try:
            for conn, log_time, data in self._reader.messages(connections=connections):
                read += 1
                yield conn, int(log_time), bytes(data)
        except ReaderError as exc:
            raise BagError(f"bag {str(self.path)!r} is damaged: {one_line(exc)}") from None
        except _DAMAGE as exc:
            raise BagError(f"bag {str(self.path)!r} is damaged: {_describe(exc)}") from None
        if read != listed:  # nothing may go missing silently (rosbag2's talker bag did)
            raise BagError(
                f"bag {str(self.path)!r}: read {read} of the {listed} messages its metadata "
                "lists; the file is damaged or laid out in a way this reader cannot read"
            )
