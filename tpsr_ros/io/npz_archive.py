"""Pickle-free ``.npz`` archives with a JSON metadata entry: the layer under model and
policy files.

An archive is ``numpy.savez`` of plain numeric arrays plus one entry ``metadata``, a 0-d
unicode array holding a JSON object with at least ``format`` and ``format_version``.
Writing goes to a temporary file next to the target, then an atomic rename, so a reader
never sees half a file and nothing is left behind on failure; an existing target is
refused unless ``force``. Reading uses ``allow_pickle=False`` and names every problem
(truncated, foreign, wrong format or version) in a ``ModelFormatError``.

Reading is bounded: nothing is inflated before it is checked. The zip directory and each
array's ``.npy`` header are read first; every array must be numeric, its declared shape
must match the bytes its member holds, the metadata must be at most
``MAX_METADATA_BYTES`` of JSON nested at most ``MAX_JSON_DEPTH`` deep, and the caller's
``expected_shapes(metadata)`` (the shapes the metadata's parameters imply) must accept
every array's shape before any array is read. A hostile file (a header declaring 2**40
values, a few MB of deflated zeros that inflate to GB, metadata nested 100000 deep) is
refused with one line.
"""

from __future__ import annotations

import json
import math
import stat
import struct
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from tokenize import TokenError
from typing import Any, BinaryIO

import numpy as np

from tpsr_ros.core.errors import ModelFormatError, one_line
from tpsr_ros.io.atomic import atomic_file

__all__ = [
    "MAX_ARRAY_BYTES",
    "MAX_JSON_DEPTH",
    "MAX_METADATA_BYTES",
    "METADATA_KEY",
    "ArrayHeader",
    "ShapeRule",
    "check_output_path",
    "jsonable",
    "metadata_size",
    "read_archive",
    "write_archive",
]

METADATA_KEY = "metadata"
MAX_METADATA_BYTES = 16 * 2**20
MAX_JSON_DEPTH = 64
MAX_ARRAY_BYTES = 2**30  # all arrays together; real models and policies are a few MB
MAX_MEMBERS = 64

_UNREADABLE = (
    OSError,
    ValueError,
    EOFError,
    KeyError,
    RuntimeError,
    OverflowError,
    NotImplementedError,  # a zip member compressed with an unsupported method
    struct.error,
    zipfile.BadZipFile,
    zlib.error,
)
"""What zipfile and numpy raise on a damaged archive; reported, never a traceback."""

ArrayHeader = tuple[tuple[int, ...], np.dtype]
ShapeRule = tuple[int | None, ...]
"""An expected shape: ``None`` where any length is allowed."""


def check_output_path(path: Path | str, *, force: bool = False) -> Path:
    """Refuse an existing output (unless ``force``) or a missing directory, before any work."""
    path = Path(path)
    if path.is_dir():
        raise ModelFormatError(f"output path {str(path)!r} is a directory")
    if path.exists() and not force:
        raise ModelFormatError(
            f"output file {str(path)!r} already exists; use --force to overwrite it"
        )
    if not path.resolve().parent.is_dir():
        raise ModelFormatError(f"output directory {str(path.resolve().parent)!r} does not exist")
    return path


def jsonable(value: Any) -> Any:
    """``value`` with numpy types, paths and non-finite floats made JSON-serialisable."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)  # JSON has no NaN or infinity
    if isinstance(value, Path):
        return str(value)
    return value


def write_archive(
    path: Path | str,
    arrays: dict[str, np.ndarray],
    metadata: dict[str, Any],
    *,
    force: bool = False,
) -> Path:
    """Write numeric ``arrays`` and JSON ``metadata`` to ``path`` atomically."""
    path = check_output_path(path, force=force)
    try:
        text = json.dumps(jsonable(metadata), allow_nan=False)
    except ValueError as exc:
        raise ModelFormatError(f"metadata cannot be stored as JSON: {one_line(exc)}") from None
    arrays = {name: np.asarray(arr) for name, arr in arrays.items()}
    if METADATA_KEY in arrays:
        raise ModelFormatError(f"an array may not be called {METADATA_KEY!r}")
    if any(arr.dtype == object for arr in arrays.values()):
        raise ModelFormatError("arrays must be numeric, not Python objects")
    arrays[METADATA_KEY] = np.array(text)
    with atomic_file(path) as handle:
        np.savez(handle, **arrays)  # type: ignore[arg-type]
        if path.exists() and not force:  # appeared while we were writing
            raise ModelFormatError(f"output file {str(path)!r} already exists; use --force")
    return path


def _json_depth_ok(text: str, limit: int) -> bool:
    """Whether brackets nest at most ``limit`` deep (strings ignored), before parsing."""
    depth, in_string, escaped = 0, False, False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            if depth > limit:
                return False
        elif char in "]}":
            depth -= 1
    return True


def _read_header(handle: BinaryIO) -> tuple[ArrayHeader, int]:
    """Shape and dtype from an ``.npy`` header, and the header's length in bytes."""
    version = np.lib.format.read_magic(handle)
    readers = {
        (1, 0): np.lib.format.read_array_header_1_0,
        (2, 0): np.lib.format.read_array_header_2_0,
    }
    if version not in readers:
        raise ValueError(f"unsupported .npy format version {version}")
    try:  # numpy parses the header as a Python literal: garbage raises anything
        shape, _, dtype = readers[version](handle)
        header = (tuple(int(n) for n in shape), np.dtype(dtype))
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError, TokenError) as exc:
        raise ValueError(f"unreadable .npy header ({type(exc).__name__})") from None
    return header, handle.tell()


def _inspect(archive: zipfile.ZipFile, path: Path) -> dict[str, ArrayHeader]:
    """Every member's declared shape and dtype, checked against its stored size."""
    infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise ModelFormatError(f"{str(path)!r} holds {len(infos)} entries: not an archive of ours")
    headers: dict[str, ArrayHeader] = {}
    total = 0
    for info in infos:
        name = info.filename.removesuffix(".npy")
        if not info.filename.endswith(".npy") or name in headers:
            raise ModelFormatError(f"{str(path)!r} holds an unexpected entry {info.filename!r}")
        with archive.open(info) as handle:
            (shape, dtype), header_bytes = _read_header(handle)
        if dtype.hasobject or dtype.kind not in "biufU":
            raise ModelFormatError(f"array {name!r} of {str(path)!r} has dtype {dtype}")
        declared = math.prod(shape) * dtype.itemsize
        if declared != info.file_size - header_bytes:
            raise ModelFormatError(
                f"array {name!r} of {str(path)!r} declares shape {shape} ({declared} bytes) "
                f"but holds {info.file_size - header_bytes} bytes: the file is corrupt"
            )
        limit = MAX_METADATA_BYTES if name == METADATA_KEY else MAX_ARRAY_BYTES
        total += declared
        if declared > limit or total > MAX_ARRAY_BYTES:
            raise ModelFormatError(
                f"{str(path)!r} declares {total} bytes of arrays, more than the {limit} "
                "this tpsr-ros reads"
            )
        headers[name] = (shape, dtype)
    return headers


def metadata_size(path: Path, where: dict[str, Any], key: str) -> int:
    """``where[key]`` as a positive integer (an array length), or a ``ModelFormatError``."""
    value = where.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ModelFormatError(f"the metadata of {str(path)!r} lacks a valid {key!r} entry")
    return value


def _check_shapes(
    path: Path, headers: Mapping[str, ArrayHeader], expected: Mapping[str, ShapeRule]
) -> None:
    """Refuse missing, unexpected and wrongly shaped arrays before any is read."""
    arrays = {name for name in headers if name != METADATA_KEY}
    if missing := sorted(set(expected) - arrays):
        raise ModelFormatError(f"{str(path)!r} lacks the arrays {missing}")
    if extra := sorted(arrays - set(expected)):
        raise ModelFormatError(f"{str(path)!r} has unexpected arrays {extra}")
    for name, rule in expected.items():
        shape = headers[name][0]
        fits = len(shape) == len(rule) and all(
            want is None or want == got for want, got in zip(rule, shape, strict=True)
        )
        if not fits:
            shown = tuple("*" if n is None else n for n in rule)
            raise ModelFormatError(
                f"array {name!r} of {str(path)!r} has shape {shape}; its metadata implies {shown}"
            )


def _parse_metadata(path: Path, raw: np.ndarray) -> dict[str, Any]:
    if raw.shape != () or raw.dtype.kind != "U":
        raise ModelFormatError(f"the metadata entry of {str(path)!r} is not a JSON string")
    text = str(raw)
    if not _json_depth_ok(text, MAX_JSON_DEPTH):
        raise ModelFormatError(
            f"the metadata of {str(path)!r} nests deeper than {MAX_JSON_DEPTH} levels"
        )
    try:
        metadata = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ModelFormatError(
            f"the metadata of {str(path)!r} is not valid JSON: {one_line(exc)}"
        ) from None
    if not isinstance(metadata, dict):
        raise ModelFormatError(f"the metadata of {str(path)!r} is not a JSON object")
    return metadata


def read_archive(
    path: Path | str,
    *,
    format_name: str,
    format_version: int | tuple[int, ...],
    expected_shapes: Callable[[dict[str, Any]], Mapping[str, ShapeRule]] | None = None,
    read_arrays: bool = True,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and check an archive of ``format_name`` at ``format_version``.

    ``expected_shapes(metadata)`` names every array the format has and the shape its
    metadata implies (raising ``ModelFormatError`` for unusable metadata); arrays are read
    only after it accepted their declared shapes. Returns ``(metadata, arrays)``;
    ``arrays`` is empty when ``read_arrays`` is false (every header still checked).
    """
    path = Path(path)
    what = format_name.removeprefix("tpsr-ros ")
    try:
        mode: int | None = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        mode = None
    except OSError as exc:  # e.g. a name too long for the file system (a -p value)
        raise ModelFormatError(
            f"{what} file {str(path)[:200]!r} cannot be opened: {exc.strerror}"
        ) from None
    if mode is not None and stat.S_ISDIR(mode):
        raise ModelFormatError(f"{what} file {str(path)!r} is a directory, not a file")
    if mode is None or not stat.S_ISREG(mode):
        raise ModelFormatError(f"{what} file {str(path)!r} does not exist")
    try:
        with path.open("rb") as handle:
            if handle.read(6) == b"\x93NUMPY":
                raise ModelFormatError(f"{str(path)!r} is a single array, not a {format_name} file")
        with zipfile.ZipFile(path) as archive:
            headers = _inspect(archive, path)
            if METADATA_KEY not in headers:
                raise ModelFormatError(
                    f"{str(path)!r} has no {METADATA_KEY!r} entry: not a {format_name} file"
                )
            metadata = _parse_metadata(path, _read_member(archive, METADATA_KEY))
            _check_format(path, metadata, format_name, format_version)
            if expected_shapes is not None:
                _check_shapes(path, headers, expected_shapes(metadata))
            arrays = {
                name: _read_member(archive, name)
                for name in headers
                if read_arrays and name != METADATA_KEY
            }
    except ModelFormatError:
        raise
    except _UNREADABLE as exc:
        raise ModelFormatError(
            f"{str(path)!r} is not a readable {what} file (truncated or foreign): "
            f"{one_line(exc)}"
        ) from None
    return metadata, arrays


def _read_member(archive: zipfile.ZipFile, name: str) -> np.ndarray:
    with archive.open(f"{name}.npy") as handle:
        array: np.ndarray = np.lib.format.read_array(handle, allow_pickle=False)
    return array


def _short(value: Any) -> str:
    """``repr(value)``, cut to 60 characters (hostile metadata may hold anything)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_format(
    path: Path, metadata: dict[str, Any], format_name: str, version: int | tuple[int, ...]
) -> None:
    what = format_name.removeprefix("tpsr-ros ")
    readable = version if isinstance(version, tuple) else (version,)
    if metadata.get("format") != format_name:
        raise ModelFormatError(
            f"{str(path)!r} is a {_short(metadata.get('format'))} file, not a {format_name!r} file"
        )
    found = metadata.get("format_version")
    if type(found) is not int or found not in readable:
        shown = " or ".join(map(str, readable))
        raise ModelFormatError(
            f"{str(path)!r} has {what} format version {_short(found)}; "
            f"this tpsr-ros reads version {shown}"
        )
