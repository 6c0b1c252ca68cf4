"""Greedy fitted-Q policies and their files.

A policy is a :class:`~tpsr_ros.core.fqi.QFunction` over the states of one representation,
plus the name of that representation's model: its SHA-256 fingerprint
(:func:`tpsr_ros.io.model_io.model_fingerprint`), or ``"true-position"`` for the
ground-truth baseline. Whoever pairs a policy with a model (evaluation, filter node)
checks the fingerprint and refuses a mismatch.

File layout (:mod:`tpsr_ros.io.npz_archive`): float64 arrays ``mean``, ``scale``,
``rotation``, ``centers``, ``width`` (one per fitted-Q member), ``weights``, int64
``group_sizes`` (centres per member) and JSON metadata ``{"format": "tpsr-ros policy",
"format_version": 2, "representation", "model_fingerprint", "model_path",
"environment", "fqi": {...}, "data": {...}, "state_dim", "n_actions", "n_centers",
"members", ...}``. Version 1 files (one member, no rotation) still load.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import tpsr_ros
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import ModelFormatError
from tpsr_ros.core.fqi import FQIConfig, QFunction
from tpsr_ros.core.planning import fit_q_on
from tpsr_ros.io.npz_archive import ShapeRule, metadata_size, read_archive, write_archive

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "REPRESENTATIONS",
    "TRUE_POSITION",
    "Policy",
    "load_policy",
    "policy_from_states",
    "save_policy",
]

FORMAT_NAME = "tpsr-ros policy"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
TRUE_POSITION = "true-position"
REPRESENTATIONS = ("tpsr", "pca", "stacked-pca", "window", TRUE_POSITION)
"""Representations a policy may name; ``stacked-pca`` and ``window`` are experiment
baselines (:mod:`tpsr_ros.core.window_baselines`) whose models are never saved."""
MAX_MAGNITUDE = 1e100
"""Bound on every stored value: fitted Q squares widths and distances, which must not overflow."""


@dataclass(frozen=True)
class Policy:
    """Greedy policy ``argmax_a Q(state, a)`` for one representation's states."""

    q: QFunction
    representation: str
    model_fingerprint: str
    environment: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.representation not in REPRESENTATIONS:
            raise ModelFormatError(
                f"unknown representation {self.representation!r}; one of {REPRESENTATIONS}"
            )

    @property
    def state_dim(self) -> int:
        """Dimension of the states the policy takes."""
        return self.q.state_dim

    @property
    def n_actions(self) -> int:
        """Number of actions."""
        return self.q.n_actions

    def action(self, state: np.ndarray) -> int:
        """Greedy action index for one state ``(state_dim,)``."""
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (self.state_dim,):
            raise ModelFormatError(
                f"the policy takes {self.state_dim}-dimensional states, got shape {state.shape}"
            )
        return int(self.q.greedy(state[None])[0])

    def check_model(self, fingerprint: str, what: str = "the model") -> None:
        """Refuse to pair this policy with a model of another fingerprint."""
        if fingerprint != self.model_fingerprint:
            raise ModelFormatError(
                f"the policy was trained for model {self.model_fingerprint[:12]}, but "
                f"{what} is {fingerprint[:12]}"
            )

    def model_path(self, explicit: str | Path | None = None) -> Path:
        """The model file to pair with: ``explicit``, else the path recorded at training.

        A missing record or a recorded path that no longer exists is refused; the caller's
        model check (:meth:`check_model`) then verifies the fingerprint.
        """
        if explicit is not None:
            return Path(explicit)
        recorded = self.metadata.get("model_path")
        if not recorded:
            raise ModelFormatError("the policy records no model path; pass --model MODEL")
        try:
            found = Path(recorded).exists()
        except (OSError, TypeError, ValueError):  # too long, not text, a NUL byte
            found = False
        if not found:
            raise ModelFormatError(
                f"the policy's model {str(recorded)[:200]!r} does not exist (relative to the "
                "current directory); pass --model MODEL"
            )
        return Path(recorded)

    def check_environment(self, environment: str) -> None:
        """Refuse an environment other than the one the policy was trained in (when known)."""
        if self.environment is not None and environment != self.environment:
            raise ModelFormatError(
                f"the policy was trained in environment {self.environment!r}, not {environment!r}"
            )


def save_policy(policy: Policy, path: Path | str, *, force: bool = False) -> Path:
    """Write ``policy`` atomically (refusing an existing ``path`` unless ``force``)."""
    q = policy.q
    arrays = {
        "mean": q.mean,
        "scale": q.scale,
        "rotation": np.eye(q.state_dim) if q.rotation is None else q.rotation,
        "centers": q.centers,
        "width": q.width,
        "weights": q.weights,
        "group_sizes": q.group_sizes,
    }
    metadata = {
        **policy.metadata,
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "representation": policy.representation,
        "model_fingerprint": policy.model_fingerprint,
        "environment": policy.environment,
        "state_dim": policy.state_dim,
        "n_actions": policy.n_actions,
        "n_centers": int(q.centers.shape[0]),
        "members": q.members,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "software": {"tpsr_ros": tpsr_ros.__version__, "numpy": np.__version__},
    }
    return write_archive(path, arrays, metadata, force=force)


def _expected_shapes(path: Path, metadata: dict[str, Any]) -> dict[str, ShapeRule]:
    """Array shapes implied by the metadata: ``state_dim``, ``n_actions``, ``n_centers``.

    Files written before ``n_centers`` was recorded leave the number of centres free (the
    archive's size limit still bounds it, and the arrays must agree with each other).
    Version 1 files have one member, a scalar width and no rotation or group sizes.
    """
    dim = metadata_size(path, metadata, "state_dim")
    actions = metadata_size(path, metadata, "n_actions")
    centers = (
        None if metadata.get("n_centers") is None else metadata_size(path, metadata, "n_centers")
    )
    shapes: dict[str, ShapeRule] = {
        "mean": (dim,),
        "scale": (dim,),
        "centers": (centers, dim),
        "width": (),
        "weights": (centers, actions),
    }
    if metadata.get("format_version") == 1:
        return shapes
    members = metadata_size(path, metadata, "members")
    return {**shapes, "width": (members,), "rotation": (dim, dim), "group_sizes": (members,)}


def load_policy(path: Path | str) -> Policy:
    """Load and validate a policy written by :func:`save_policy`."""
    path = Path(path)
    metadata, arrays = read_archive(
        path,
        format_name=FORMAT_NAME,
        format_version=READABLE_VERSIONS,
        expected_shapes=lambda meta: _expected_shapes(path, meta),
    )
    sizes = arrays.pop("group_sizes", None)
    for name, array in arrays.items():
        if array.dtype != np.float64 or not np.all(np.isfinite(array)):
            raise ModelFormatError(f"array {name!r} of {str(path)!r} is not finite float64")
        if np.any(np.abs(array) > MAX_MAGNITUDE):
            raise ModelFormatError(
                f"array {name!r} of {str(path)!r} holds values beyond {MAX_MAGNITUDE:g}: corrupt"
            )
    for key in ("representation", "environment"):
        if metadata.get(key) is not None and not isinstance(metadata.get(key), str):
            raise ModelFormatError(f"the metadata of {str(path)!r} lacks a valid {key!r} entry")
    mean, scale, centers, weights = (arrays[k] for k in ("mean", "scale", "centers", "weights"))
    width = np.atleast_1d(arrays["width"])
    rotation = arrays.get("rotation")
    dim = mean.shape[0] if mean.ndim == 1 else -1
    if sizes is None:
        sizes = np.array([len(centers)])
    elif sizes.dtype != np.int64 or np.any(sizes < 1) or sizes.sum() != len(centers):
        raise ModelFormatError(
            f"{str(path)!r}: 'group_sizes' must be positive int64 counts summing to the centres"
        )
    consistent = (
        mean.ndim == 1
        and scale.shape == mean.shape
        and np.all(scale > 0)
        and centers.ndim == 2
        and centers.shape[1] == dim
        and weights.ndim == 2
        and weights.shape[0] == centers.shape[0]
        and width.shape == sizes.shape
        and np.all(width > 1.0 / MAX_MAGNITUDE)
        and np.all(scale > 1.0 / MAX_MAGNITUDE)
        and metadata.get("state_dim") == dim
        and metadata.get("n_actions") == weights.shape[1]
    )
    if not consistent:
        raise ModelFormatError(f"{str(path)!r} has inconsistent array shapes or metadata")
    fingerprint = metadata.get("model_fingerprint")
    if not isinstance(fingerprint, str) or not fingerprint:
        raise ModelFormatError(f"{str(path)!r} does not name the model it belongs to")
    if rotation is not None and np.array_equal(rotation, np.eye(dim)):
        rotation = None  # standardised states: skip the identity product
    q = QFunction(mean, scale, centers, width, weights, rotation, sizes)
    known = {f.name for f in dataclasses.fields(Policy)} | {"format", "format_version"}
    return Policy(
        q=q,
        representation=str(metadata.get("representation")),
        model_fingerprint=fingerprint,
        environment=metadata.get("environment"),
        metadata={k: v for k, v in metadata.items() if k not in known},
    )


def policy_from_states(
    states: np.ndarray,
    trajectory: Trajectory,
    config: FQIConfig,
    *,
    representation: str,
    fingerprint: str,
    environment: str | None,
    metadata: dict[str, Any] | None = None,
    skip_unknown: bool = False,
    tracking_s: float = 0.0,
) -> Policy:
    """The greedy policy of fitted Q on ``states`` tracked over ``trajectory`` (with rewards).

    The metadata record the fitted-Q configuration used (a larger ridge than ``config``'s
    if the fit diverged: :func:`~tpsr_ros.core.planning.fit_q_on`; ``member_ridges``, the
    ridge of each ensemble member), the data and the timings, after the entries of
    ``metadata`` (model path, preset, reward source).
    ``skip_unknown``: see :func:`~tpsr_ros.core.planning.transitions`.
    """
    start = time.perf_counter()
    q, used, n_transitions = fit_q_on(states, trajectory, config, skip_unknown=skip_unknown)
    return Policy(
        q=q,
        representation=representation,
        model_fingerprint=fingerprint,
        environment=environment,
        metadata={
            **(metadata or {}),
            "fqi": {**used.to_dict(), "member_ridges": list(q.ridges or ())},
            "data": {**trajectory.summary(), "transitions": n_transitions},
            "timing_s": {"tracking": tracking_s, "fitted_q": time.perf_counter() - start},
        },
    )
