"""Pickle-free ``.npz`` archives with a JSON metadata entry: the layer under model and
policy files.

An archive is ``numpy.savez`` of plain numeric arrays plus one entry ``metadata``, a 0-d
unicode array holding a JSON object with at least ``format`` and ``format_version``.
Writing goes to a temporary file next to the target, then an atomic rename, so a reader
never sees half a file and nothing is left behind on failure; an existing target is
refused unless ``force``. Reading uses ``allow_pickle=False`` and names every problem
(truncated, foreign, wrong format or version) in a ``ModelFormatError``.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.errors import ModelFormatError

__all__ = ["METADATA_KEY", "check_output_path", "jsonable", "read_archive", "write_archive"]

METADATA_KEY = "metadata"


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
        raise ModelFormatError(f"metadata cannot be stored as JSON: {exc}") from None
    arrays = {name: np.asarray(arr) for name, arr in arrays.items()}
    if METADATA_KEY in arrays:
        raise ModelFormatError(f"an array may not be called {METADATA_KEY!r}")
    if any(arr.dtype == object for arr in arrays.values()):
        raise ModelFormatError("arrays must be numeric, not Python objects")
    arrays[METADATA_KEY] = np.array(text)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=".tmp", dir=path.resolve().parent
    )
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as handle:
            np.savez(handle, **arrays)  # type: ignore[arg-type]
            handle.flush()
            os.fsync(handle.fileno())
        if path.exists() and not force:  # appeared while we were writing
            raise ModelFormatError(f"output file {str(path)!r} already exists; use --force")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_archive(
    path: Path | str, *, format_name: str, format_version: int
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and check an archive of ``format_name`` at ``format_version``.

    Returns ``(metadata, arrays)``; the arrays still need the caller's shape checks.
    """
    path = Path(path)
    what = format_name.removeprefix("tpsr-ros ")
    if not path.is_file():
        raise ModelFormatError(f"{what} file {str(path)!r} does not exist")
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.ndarray):
            raise ModelFormatError(f"{str(path)!r} is a single array, not a {format_name} file")
        with loaded as npz:
            arrays = {name: npz[name] for name in npz.files}
    except ModelFormatError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, RuntimeError) as exc:
        raise ModelFormatError(
            f"{str(path)!r} is not a readable {what} file (truncated or foreign): {exc}"
        ) from None
    if METADATA_KEY not in arrays:
        raise ModelFormatError(
            f"{str(path)!r} has no {METADATA_KEY!r} entry: not a {format_name} file"
        )
    raw = arrays.pop(METADATA_KEY)
    if raw.shape != () or raw.dtype.kind != "U":
        raise ModelFormatError(f"the metadata entry of {str(path)!r} is not a JSON string")
    try:
        metadata = json.loads(str(raw))
    except json.JSONDecodeError as exc:
        raise ModelFormatError(f"the metadata of {str(path)!r} is not valid JSON: {exc}") from None
    if not isinstance(metadata, dict):
        raise ModelFormatError(f"the metadata of {str(path)!r} is not a JSON object")
    if metadata.get("format") != format_name:
        raise ModelFormatError(
            f"{str(path)!r} is a {metadata.get('format')!r} file, not a {format_name!r} file"
        )
    version = metadata.get("format_version")
    if version != format_version:
        raise ModelFormatError(
            f"{str(path)!r} has {what} format version {version!r}; this tpsr-ros reads "
            f"version {format_version}"
        )
    return metadata, arrays
