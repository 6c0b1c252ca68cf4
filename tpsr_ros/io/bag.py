"""rosbag2 MCAP bags: the one module the generator, recorder, player and learner share.

A bag is a rosbag2 directory (``metadata.yaml`` + ``<name>.mcap``, storage ``mcap``,
serialisation ``cdr``) written with ``rosbags``; MCAP chunks are zstd-compressed, which
``ros2 bag``, ``rosbags`` and ``mcap`` all read transparently.

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

from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import Reader, ReaderError, Writer, WriterError
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

from tpsr_ros.core.errors import BagError
from tpsr_ros.io.messages import deserialize, jazzy_typestore, serialize
from tpsr_ros.safe_yaml import YamlInputError, load_yaml

__all__ = ["BagMessage", "BagReader", "BagWriter", "check_bag_path_free", "read_bag_metadata"]

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
    text = str(exc) or type(exc).__name__
    return f"{type(exc).__name__}: {text[:120]}"


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


class BagWriter:
    """Write serialised ROS 2 messages into a new rosbag2 MCAP bag.

    Use as a context manager. Topics are declared once with :meth:`add_topic`; messages
    are written as CDR bytes (:meth:`write`, what a recorder receives) or as message
    objects (:meth:`write_message`, serialised here).
    """

    def __init__(self, path: Path | str, *, compress: bool = True) -> None:
        self.path = check_bag_path_free(Path(path))
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections: dict[str, Connection] = {}
        self._types: dict[str, str] = {}
        self._open = False
        self.message_count = 0

    def open(self) -> BagWriter:
        """Create the bag directory and MCAP file."""
        try:
            self._writer.open()
        except (WriterError, OSError) as exc:
            raise BagError(f"cannot create bag {str(self.path)!r}: {exc}") from None
        self._open = True
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

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """Declare ``topic`` with ROS type ``msgtype``; a clashing redeclaration is refused."""
        if topic in self._types:
            if self._types[topic] != msgtype:
                raise BagError(
                    f"topic {topic!r} already has type {self._types[topic]}, not {msgtype}"
                )
            return
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype, typestore=jazzy_typestore(), offered_qos_profiles=list(qos)
        )
        self._types[topic] = msgtype

    def set_custom_data(self, key: str, value: str) -> None:
        """Store a string in ``metadata.yaml``'s ``custom_data`` (e.g. generator settings)."""
        self._writer.set_custom_data(key, value)

    def has_topic(self, topic: str) -> bool:
        """Whether ``topic`` was declared."""
        return topic in self._types

    def write(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> None:
        """Append CDR bytes on a declared topic with log time ``stamp_ns``."""
        try:
            connection = self._connections[topic]
        except KeyError:
            raise BagError(f"topic {topic!r} was not declared with add_topic") from None
        self._writer.write(connection, int(stamp_ns), data)
        self.message_count += 1

    def write_message(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialise ``msg`` with the topic's declared type and append it."""
        if topic not in self._types:
            raise BagError(f"topic {topic!r} was not declared with add_topic")
        self.write(topic, stamp_ns, serialize(msg, self._types[topic]))

    def flush(self) -> None:
        """Close the pending MCAP chunk and hand everything written so far to the OS.

        After a hard kill the ``.mcap`` then holds every message up to this call; see
        ``tpsr_ros.bag_recover`` for reading such a bag.
        """
        storage = getattr(self._writer, "storage", None)
        if storage is None:
            return
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and chunk.bio.tell():
            storage.close_chunk()
        storage.bio.flush()

    def close(self) -> None:
        """Finish the MCAP summary and write ``metadata.yaml``."""
        if self._open:
            self._open = False
            self._writer.close()

    def abort(self) -> None:
        """Discard the bag: close files and remove the directory this writer created."""
        if self._open:
            self._open = False
            try:
                self._writer.close()
            finally:
                shutil.rmtree(self.path, ignore_errors=True)


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

    ``metadata.yaml`` is read bounded (:mod:`tpsr_ros.safe_yaml`: UTF-8, 16 MiB, no
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
    return info


class BagReader:
    """Read a rosbag2 MCAP bag; anything else is refused with a ``BagError``."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        info = read_bag_metadata(self.path)
        self._custom_data = {str(k): str(v) for k, v in (info.get("custom_data") or {}).items()}
        storage = info.get("storage_identifier")
        if storage != "mcap":
            raise BagError(f"bag {str(self.path)!r} uses storage {storage!r}, not mcap")
        self._reader = Reader(self.path)
        try:
            self._reader.open()
        except (ReaderError, OSError) as exc:
            raise BagError(f"cannot open bag {str(self.path)!r}: {exc}") from None
        except _DAMAGE as exc:
            damage = _describe(exc)
            raise BagError(f"cannot open bag {str(self.path)!r}: damaged ({damage})") from None

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
    def start_time_ns(self) -> int:
        """Log time of the first message."""
        return int(self._reader.start_time)

    @property
    def end_time_ns(self) -> int:
        """Log time just after the last message."""
        return int(self._reader.end_time)

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
        wanted = None if topics is None else set(topics)
        connections = [
            c for c in self._reader.connections if wanted is None or c.topic in wanted
        ]
        if wanted is not None and not connections:
            return
        listed = sum(c.msgcount for c in connections)
        read = 0
        try:
            for conn, log_time, data in self._reader.messages(connections=connections):
                read += 1
                yield BagMessage(conn.topic, conn.msgtype, int(log_time), bytes(data))
        except ReaderError as exc:
            raise BagError(f"bag {str(self.path)!r} is damaged: {exc}") from None
        except _DAMAGE as exc:
            raise BagError(f"bag {str(self.path)!r} is damaged: {_describe(exc)}") from None
        if read != listed:  # nothing may go missing silently (rosbag2's talker bag did)
            raise BagError(
                f"bag {str(self.path)!r}: read {read} of the {listed} messages its metadata "
                "lists; the file is damaged or laid out in a way this reader cannot read"
            )
