"""Model files: a state model (TPSR or PCA) in a pickle-free ``.npz`` with JSON metadata.

Layout: ``numpy.savez`` of plain numeric arrays (the model's :meth:`to_arrays`) plus one
entry ``metadata``, a 0-d unicode array holding a JSON object::

    {"format": "tpsr-ros model", "format_version": 1, "method": "tpsr" | "pca",
     "parameters": {...every parameter...}, "summary": {...singular values, explained
     variance, timings...}, "n_actions": 25, "observation": {"size": 768, ...},
     "training": {...bags, steps, episodes, stamps, environment, topics...},
     "input": {...} (models learned with --step-period only),
     "view": {"points": 1000, "pose_dim": 0 | 2 | 4, "pose_frame": "map"} (models with the
       viewer's read-outs: arrays view_image, view_axes, view_center, view_points[, view_pose]),
     "basis": {"rank": r, "history_width": w, "test_width": w[, "sketch_width": s]} (TPSRs
       with the whitenings and centres a refit keeps: arrays basis_{history,test,obs}_{mean,
       components,eigenvalues,ratio}, basis_{history,test}_centers[, the sketch of P_TH a
       refit from statistics projects on: basis_sketch_{test,history}];
       :mod:`tpsr_ros.core.fit_basis`),
     "preset": {"name": "best", "changed": {...}[, "turning": true]} (descriptive; learner
       fit writes it),
     "created": "...", "software": {"tpsr_ros": "0.1.0", "numpy": "..."}}

``input`` (:class:`tpsr_ros.io.stream_spec.StreamSpec`) is what a model learned from robot bags
remembers about its streams: camera topic, type and preprocessing, command topic, type and
action codebook, and the step grid. Models without it (all older files, and every model
learned by exact-stamp pairing of simulator bags) read 16x16 rgb8 images and the
simulator's 25 actions, as before; :func:`model_stream_spec` returns None for them.

The archive layer (atomic no-clobber writes, ``allow_pickle=False`` reads, format name and
version checks) is :mod:`tpsr_ros.io.npz_archive`. ``load_model`` also checks the method and
that every required array is present with a real floating dtype, finite, and of
consistent shape, naming the problem in a :class:`~tpsr_ros.core.errors.ModelFormatError`.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

import tpsr_ros
from tpsr_ros.core.errors import ConfigError, ModelFormatError, TpsrError
from tpsr_ros.core.fit_basis import FitBasis, basis_shapes
from tpsr_ros.core.pca_baseline import PCAModel
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.core.tpsr import TPSRModel
from tpsr_ros.core.view_readout import ViewReadout
from tpsr_ros.io.npz_archive import (
    ShapeRule,
    check_output_path,
    metadata_size,
    read_archive,
    write_archive,
)
from tpsr_ros.io.stream_spec import StreamSpec

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "METHODS",
    "ModelFile",
    "check_output_path",
    "load_model",
    "metadata_field",
    "model_fingerprint",
    "model_stream_spec",
    "open_model",
    "read_metadata",
    "save_model",
]

FORMAT_NAME = "tpsr-ros model"
FORMAT_VERSION = 1
METHODS: dict[str, type[TPSRModel] | type[PCAModel]] = {"tpsr": TPSRModel, "pca": PCAModel}
_INTEGER_ARRAYS = {"n_actions"}


def metadata_field(value: Any, *keys: str) -> Any:
    """``value[k1][k2]...``; None where a level is missing or not a mapping.

    The descriptive metadata (training data, summary, software) is not needed to load a
    model and is not validated by :func:`load_model`; a file may carry anything there.
    """
    for key in keys:
        if not isinstance(value, dict):
            return None
        value = value.get(key)
    return value


def save_model(
    model: StateModel,
    path: Path | str,
    *,
    training: dict[str, Any] | None = None,
    inputs: StreamSpec | None = None,
    preset: dict[str, Any] | None = None,
    view: ViewReadout | None = None,
    force: bool = False,
) -> Path:
    """Write ``model`` to ``path`` atomically.

    ``training`` describes the data (bags, stamps...); ``inputs`` the streams of a model
    learned on the step grid (stored as ``"input"``; checked against the model first);
    ``preset`` the named settings the fit started from and what its options changed
    (``{"name": ..., "changed": {...}}``, shown by ``learner info``); ``view`` the viewer's
    read-outs of its state (:mod:`tpsr_ros.core.view_readout`), outside its fingerprint.
    """
    if model.method not in METHODS:
        raise ModelFormatError(
            f"{model.method} models are experiment baselines (learner experiment --methods "
            f"{model.method}) and cannot be saved; model files hold {' or '.join(METHODS)}"
        )
    scaling = "rgb8 pixel values / 255, row-major (height, width, channel)"
    if inputs is not None:
        _check_inputs(inputs, model.obs_size, model.n_actions, "the model to save")
        scaling = "pixels resized by area averaging, / max value, row-major (h, w, channel)"
    metadata: dict[str, Any] = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "method": model.method,
        "parameters": model.parameters(),
        "summary": model.summary(),
        "n_actions": model.n_actions,
        "state_dim": model.state_dim,
        "observation": {
            "size": model.obs_size,
            "scaling": scaling,
        },
        "training": training or {},
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "software": {"tpsr_ros": tpsr_ros.__version__, "numpy": np.__version__},
    }
    if inputs is not None:
        metadata["input"] = inputs.as_dict()
    if preset is not None:
        metadata["preset"] = preset
    arrays = model.to_arrays()
    if view is not None:
        if view.center.shape != (model.state_dim,) or view.obs_size != model.obs_size:
            raise ModelFormatError("the view read-out was fitted for another model's states")
        metadata["view"] = {
            "points": view.points.shape[0],
            "pose_dim": 0 if view.pose is None else view.pose.shape[1],
            "pose_frame": view.pose_frame,
        }
        arrays.update(view.to_arrays())
    basis = getattr(model, "basis", None)
    if basis is not None:
        metadata["basis"] = basis.metadata()
        arrays.update(basis.to_arrays())
    return write_archive(path, arrays, metadata, force=force)


def _check_inputs(spec: StreamSpec, obs_size: int, n_actions: int, what: str) -> None:
    if spec.preprocessing.size != obs_size:
        raise ModelFormatError(
            f"{what} takes {obs_size} observation values, but its input preprocessing makes "
            f"{spec.preprocessing.size}"
        )
    if len(spec.codebook) != n_actions:
        raise ModelFormatError(
            f"{what} has {n_actions} actions, but its codebook {len(spec.codebook)} codes"
        )


def model_stream_spec(path: Path | str, metadata: dict[str, Any]) -> StreamSpec | None:
    """The validated ``"input"`` entry of a model's metadata; None for exact-pairing models."""
    if "input" not in metadata:
        return None
    try:
        spec = StreamSpec.from_dict(metadata["input"])
    except ConfigError as exc:
        raise ModelFormatError(f"the input entry of {str(path)!r} is invalid: {exc}") from None
    observation = metadata.get("observation")
    size = observation.get("size") if isinstance(observation, dict) else None
    size = size if isinstance(size, int) else -1
    _check_inputs(spec, size, metadata["n_actions"], repr(str(path)))
    return spec


def _open_arrays(
    path: Path, *, read_arrays: bool = True
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    return read_archive(
        path,
        format_name=FORMAT_NAME,
        format_version=FORMAT_VERSION,
        expected_shapes=lambda metadata: _expected_shapes(path, metadata),
        read_arrays=read_arrays,
    )


def _expected_shapes(path: Path, metadata: dict[str, Any]) -> dict[str, ShapeRule]:
    """The shape of every array, implied by the metadata alone (checked before reading)."""
    method = _check_metadata(path, metadata)
    parameters = metadata["parameters"]
    observation = metadata.get("observation")
    if not isinstance(observation, dict):
        raise ModelFormatError(f"the metadata of {str(path)!r} lacks a valid 'observation' entry")
    k = metadata_size(path, observation, "size")
    if method == "pca":
        dim = metadata_size(path, parameters, "dim")
        return {
            "mean": (k,),
            "components": (k, dim),
            "eigenvalues": (dim,),
            "explained_variance_ratio": (dim,),
            "n_actions": (),
            **_view_shapes(path, metadata, k),
        }
    n_actions = metadata_size(path, metadata, "n_actions")
    r, d_o, d_ht, l_o = (
        metadata_size(path, parameters, key) for key in ("rank", "obs_dim", "ht_dim", "obs_centers")
    )
    shapes: dict[str, ShapeRule] = {
        "obs_mean": (k,),
        "obs_whitening": (k, d_o),
        "obs_centers": (l_o, d_o),
        "b_star": (r,),
        "b_inf": (r,),
        "B": (n_actions, l_o, r, r),
        "singular_values": (None,),
        "explained_variance_obs": (d_o,),
        "explained_variance_history": (d_ht,),
        "explained_variance_test": (d_ht,),
    }
    clip = parameters.get("state_clip_quantile", 0)
    if isinstance(clip, (int, float)) and not isinstance(clip, bool) and clip > 0:
        shapes["state_box"] = (2, r)
    return shapes | _view_shapes(path, metadata, k) | _basis_shapes(path, metadata, k)


def _basis_shapes(path: Path, metadata: dict[str, Any], k: int) -> dict[str, ShapeRule]:
    """The shapes of a TPSR's frozen basis (none when the metadata has no ``basis``)."""
    basis = metadata.get("basis")
    if basis is None:
        return {}
    if not isinstance(basis, dict):
        raise ModelFormatError(f"the metadata of {str(path)!r} has an invalid 'basis' entry")
    for key in ("rank", "history_width", "test_width"):
        metadata_size(path, basis, key)
    if "sketch_width" in basis:
        metadata_size(path, basis, "sketch_width")
    parameters = metadata["parameters"]
    for key in ("history_length", "test_length", "ht_dim", "obs_dim", "ht_centers"):
        metadata_size(path, parameters, key)
    if basis["rank"] > parameters["ht_centers"]:
        raise ModelFormatError(f"the 'basis' entry of {str(path)!r} has a rank above its centres")
    return dict(basis_shapes(parameters, basis, k))


def _view_shapes(path: Path, metadata: dict[str, Any], k: int) -> dict[str, ShapeRule]:
    """The shapes of the viewer's read-out arrays (none when the metadata has no ``view``)."""
    view = metadata.get("view")
    if view is None:
        return {}
    if not isinstance(view, dict) or not isinstance(view.get("pose_frame"), str):
        raise ModelFormatError(f"the metadata of {str(path)!r} has an invalid 'view' entry")
    r = metadata_size(path, metadata, "state_dim")
    n_actions = metadata_size(path, metadata, "n_actions")
    pose_dim = view.get("pose_dim")
    if pose_dim not in (0, 2, 4) or isinstance(pose_dim, bool):
        raise ModelFormatError(f"the 'view' entry of {str(path)!r} has pose_dim {pose_dim!r}")
    shapes: dict[str, ShapeRule] = {
        "view_image": (n_actions + 1, r + 1, k),
        "view_axes": (r, 3),
        "view_center": (r,),
        "view_points": (metadata_size(path, view, "points"), 3),
    }
    if pose_dim:
        shapes["view_pose"] = (r + 1, pose_dim)
    return shapes


def _check_metadata(path: Path, metadata: dict[str, Any]) -> str:
    method = metadata.get("method")
    if not isinstance(method, str) or method not in METHODS:
        raise ModelFormatError(
            f"{str(path)!r} holds method {str(method)[:40]!r}, not one of {sorted(METHODS)}"
        )
    for key, kind in (("parameters", dict), ("summary", dict), ("n_actions", int)):
        if not isinstance(metadata.get(key), kind):
            raise ModelFormatError(f"the metadata of {str(path)!r} lacks a valid {key!r} entry")
    return str(method)


def read_metadata(path: Path | str) -> dict[str, Any]:
    """Read the validated metadata of a model file (arrays are checked by :func:`load_model`).

    The arrays' headers and shapes are checked; their values are not read.
    """
    path = Path(path)
    metadata, _ = _open_arrays(path, read_arrays=False)
    _check_metadata(path, metadata)
    model_stream_spec(path, metadata)
    return metadata


@dataclass(frozen=True, eq=False)
class ModelFile:
    """A model archive read and validated once, with everything stored beside the model.

    Open it with :func:`open_model` and hand it along: whoever needs the model, its
    metadata, its input streams or its fingerprint reads them here, never from the file
    again (like rosbags' ``AnyReader``, which parses a bag once for every reader).
    """

    path: Path
    model: TPSRModel | PCAModel
    metadata: dict[str, Any]
    spec: StreamSpec | None
    """The input streams of a model learned on the step grid; None: exact-stamp pairing."""
    fingerprint: str
    """:func:`model_fingerprint` of the model, what a policy names."""
    view: ViewReadout | None = None
    """The viewer's read-outs of the state; None for files written without them."""

    @property
    def training(self) -> dict[str, Any]:
        """The metadata's description of the training data (empty when absent)."""
        training = self.metadata.get("training")
        return training if isinstance(training, dict) else {}

    @property
    def environment(self) -> str | None:
        """The simulator environment of the training data, when it was one environment."""
        environment = self.training.get("environment")
        return environment if isinstance(environment, str) else None

    @property
    def vertical_half_extent(self) -> float | None:
        """The simulated camera's vertical half-extent of the training bags, when they were
        generated with one (models written before it was recorded: None)."""
        value = self.training.get("vertical_half_extent")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return None
        return float(value)


def open_model(path: Path | str) -> ModelFile:
    """Read and validate a model file written by :func:`save_model`, once."""
    path = Path(path)
    metadata, arrays = _open_arrays(path)
    method = _check_metadata(path, metadata)
    spec = model_stream_spec(path, metadata)
    # read_archive has checked that the arrays are exactly those of _expected_shapes
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
    view_arrays = {name: arrays.pop(name) for name in list(arrays) if name.startswith("view_")}
    basis_arrays = {name: arrays.pop(name) for name in list(arrays) if name.startswith("basis_")}
    try:
        model = METHODS[method].from_arrays(arrays, metadata["parameters"], metadata["summary"])
        view = _view_readout(view_arrays, metadata)
        if basis_arrays and isinstance(model, TPSRModel):
            basis_config = replace(model.config, rank=metadata["basis"]["rank"])
            basis = FitBasis.from_arrays(basis_arrays, basis_config, model.obs_centers)
            model = replace(model, basis=basis)
    except TpsrError as exc:
        raise ModelFormatError(f"{str(path)!r} is inconsistent: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFormatError(f"{str(path)!r} is inconsistent: {exc!r}") from None
    if model.n_actions != metadata["n_actions"]:
        raise ModelFormatError(
            f"{str(path)!r} declares {metadata['n_actions']} actions but its arrays hold "
            f"{model.n_actions}"
        )
    if view is not None and view.center.shape != (model.state_dim,):
        raise ModelFormatError(f"{str(path)!r}: the view read-out does not fit the model's states")
    return ModelFile(path, model, metadata, spec, model_fingerprint(model), view)


def _view_readout(arrays: dict[str, np.ndarray], metadata: dict[str, Any]) -> ViewReadout | None:
    """The viewer's read-outs from their arrays (shapes already checked), or None."""
    if not arrays:
        return None
    return ViewReadout(
        image=arrays["view_image"],
        pose=arrays.get("view_pose"),
        axes=arrays["view_axes"],
        center=arrays["view_center"],
        points=arrays["view_points"],
        pose_frame=metadata["view"]["pose_frame"],
    )


def load_model(path: Path | str) -> TPSRModel | PCAModel:
    """Load and validate a model written by :func:`save_model` (:func:`open_model`'s model)."""
    return open_model(path).model


def model_fingerprint(model: StateModel) -> str:
    """SHA-256 of a model's arrays (names, dtypes, shapes, bytes): what a policy names."""
    digest = hashlib.sha256()
    for name, array in sorted(model.to_arrays().items()):
        array = np.ascontiguousarray(array)
        digest.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()
