"""Model files: a state model (TPSR or PCA) in a pickle-free ``.npz`` with JSON metadata.

Layout: ``numpy.savez`` of plain numeric arrays (the model's :meth:`to_arrays`) plus one
entry ``metadata``, a 0-d unicode array holding a JSON object::

    {"format": "tpsr-ros model", "format_version": 1, "method": "tpsr" | "pca",
     "parameters": {...every parameter...}, "summary": {...singular values, explained
     variance, timings...}, "n_actions": 25, "observation": {"size": 768, ...},
     "training": {...bags, steps, episodes, stamps, environment, topics...},
     "created": "...", "software": {"tpsr_ros": "0.1.0", "numpy": "..."}}

``load_model`` opens the file with ``allow_pickle=False`` and checks, naming the problem in
a :class:`~tpsr_ros.errors.ModelFormatError`: that it is a zip of arrays, the metadata,
the format name and version (both versions named on a mismatch), the method, that every
required array is present with a real floating dtype, finite, and of consistent shape.
``save_model`` writes a temporary file next to the target and renames it into place, so a
reader never sees half a file and nothing is left behind on failure; an existing target is
refused unless ``force``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

import tpsr_ros
from tpsr_ros.errors import ModelFormatError, TpsrError
from tpsr_ros.pca_baseline import PCAModel
from tpsr_ros.state_model import StateModel
from tpsr_ros.tpsr import TPSRModel

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "METHODS",
    "check_output_path",
    "load_model",
    "read_metadata",
    "save_model",
]

FORMAT_NAME = "tpsr-ros model"
FORMAT_VERSION = 1
METADATA_KEY = "metadata"
METHODS: dict[str, type[TPSRModel] | type[PCAModel]] = {"tpsr": TPSRModel, "pca": PCAModel}
_REQUIRED_ARRAYS = {
    "tpsr": TPSRModel.ARRAY_NAMES,
    "pca": ("mean", "components", "eigenvalues", "explained_variance_ratio", "n_actions"),
}
_INTEGER_ARRAYS = {"n_actions"}


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


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)  # JSON has no NaN or infinity
    if isinstance(value, Path):
        return str(value)
    return value


def save_model(
    model: StateModel,
    path: Path | str,
    *,
    training: dict[str, Any] | None = None,
    force: bool = False,
) -> Path:
    """Write ``model`` to ``path`` atomically; ``training`` describes the data (bags, stamps...)."""
    path = check_output_path(path, force=force)
    metadata = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "method": model.method,
        "parameters": model.parameters(),
        "summary": model.summary(),
        "n_actions": model.n_actions,
        "state_dim": model.state_dim,
        "observation": {
            "size": model.obs_size,
            "scaling": "rgb8 pixel values / 255, row-major (height, width, channel)",
        },
        "training": training or {},
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "software": {"tpsr_ros": tpsr_ros.__version__, "numpy": np.__version__},
    }
    try:
        text = json.dumps(_jsonable(metadata), allow_nan=False)
    except ValueError as exc:
        raise ModelFormatError(f"model metadata cannot be stored as JSON: {exc}") from None
    arrays = {name: np.asarray(arr) for name, arr in model.to_arrays().items()}
    if METADATA_KEY in arrays:
        raise ModelFormatError(f"a model array may not be called {METADATA_KEY!r}")
    if any(arr.dtype == object for arr in arrays.values()):
        raise ModelFormatError("model arrays must be numeric, not Python objects")
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


def _open_arrays(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    if not path.is_file():
        raise ModelFormatError(f"model file {str(path)!r} does not exist")
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.ndarray):
            raise ModelFormatError(f"{str(path)!r} is a single array, not a tpsr-ros model")
        with loaded as npz:
            arrays = {name: npz[name] for name in npz.files}
    except ModelFormatError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, RuntimeError) as exc:
        raise ModelFormatError(
            f"{str(path)!r} is not a readable model file (truncated or foreign): {exc}"
        ) from None
    if METADATA_KEY not in arrays:
        raise ModelFormatError(f"{str(path)!r} has no {METADATA_KEY!r} entry: not a tpsr-ros model")
    raw = arrays.pop(METADATA_KEY)
    if raw.shape != () or raw.dtype.kind != "U":
        raise ModelFormatError(f"the metadata entry of {str(path)!r} is not a JSON string")
    try:
        metadata = json.loads(str(raw))
    except json.JSONDecodeError as exc:
        raise ModelFormatError(f"the metadata of {str(path)!r} is not valid JSON: {exc}") from None
    if not isinstance(metadata, dict):
        raise ModelFormatError(f"the metadata of {str(path)!r} is not a JSON object")
    return metadata, arrays


def _check_metadata(path: Path, metadata: dict[str, Any]) -> str:
    if metadata.get("format") != FORMAT_NAME:
        raise ModelFormatError(
            f"{str(path)!r} is a {metadata.get('format')!r} file, not a {FORMAT_NAME!r} file"
        )
    version = metadata.get("format_version")
    if version != FORMAT_VERSION:
        raise ModelFormatError(
            f"{str(path)!r} has model format version {version!r}; this tpsr-ros reads "
            f"version {FORMAT_VERSION}"
        )
    method = metadata.get("method")
    if method not in METHODS:
        raise ModelFormatError(
            f"{str(path)!r} holds method {method!r}, not one of {sorted(METHODS)}"
        )
    for key, kind in (("parameters", dict), ("summary", dict), ("n_actions", int)):
        if not isinstance(metadata.get(key), kind):
            raise ModelFormatError(f"the metadata of {str(path)!r} lacks a valid {key!r} entry")
    return str(method)


def read_metadata(path: Path | str) -> dict[str, Any]:
    """Read the validated metadata of a model file (arrays are checked by :func:`load_model`)."""
    path = Path(path)
    metadata, _ = _open_arrays(path)
    _check_metadata(path, metadata)
    return metadata


def load_model(path: Path | str) -> TPSRModel | PCAModel:
    """Load and validate a model written by :func:`save_model`."""
    path = Path(path)
    metadata, arrays = _open_arrays(path)
    method = _check_metadata(path, metadata)
    required = _REQUIRED_ARRAYS[method]
    if missing := [name for name in required if name not in arrays]:
        raise ModelFormatError(f"{str(path)!r} lacks the {method} arrays {missing}")
    if extra := sorted(set(arrays) - set(required)):
        raise ModelFormatError(f"{str(path)!r} has unexpected arrays {extra}")
    for name, arr in arrays.items():
        if name in _INTEGER_ARRAYS:
            if arr.dtype.kind not in "iu" or arr.shape != ():
                raise ModelFormatError(f"array {name!r} of {str(path)!r} is not an integer scalar")
            continue
        if arr.dtype != np.float64:
            raise ModelFormatError(
                f"array {name!r} of {str(path)!r} has dtype {arr.dtype}, expected float64"
            )
        if not np.isfinite(arr).all():
            raise ModelFormatError(f"array {name!r} of {str(path)!r} contains non-finite values")
    try:
        model = METHODS[method].from_arrays(arrays, metadata["parameters"], metadata["summary"])
    except TpsrError as exc:
        raise ModelFormatError(f"{str(path)!r} is inconsistent: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFormatError(f"{str(path)!r} is inconsistent: {exc!r}") from None
    if model.n_actions != metadata["n_actions"]:
        raise ModelFormatError(
            f"{str(path)!r} declares {metadata['n_actions']} actions but its arrays hold "
            f"{model.n_actions}"
        )
    return model
