"""The interface every state model (TPSR, PCA baseline) offers to what comes downstream.

Fitted Q-iteration, evaluation, plots and the filter node only need: the state of a model
that has seen nothing yet, a one-step update ``(state, action, observation) -> state`` and a
batch version over a trajectory, the state dimension, and the data needed to save the model.
Both :class:`tpsr_ros.core.tpsr.TPSRModel` and :class:`tpsr_ros.core.pca_baseline.PCAModel` satisfy
:class:`StateModel`, so code written against it treats them alike.

Conventions: an observation is a float64 vector of ``obs_size`` values produced by
:func:`tpsr_ros.core.episodes.image_to_observation` (pixel values / 255); an action is an integer
index ``0 .. n_actions - 1``. ``track`` returns, for step ``s``, the state *after* the pair
``(a_s, o_s)`` has been incorporated.

A model whose state carries memory needed only by its next update (the buffer of the
finite-window predictive state, :mod:`tpsr_ros.core.window_baselines`) puts it after the
coordinates the planner should see and says how many those are in ``planner_dim``
(:func:`planner_dim`; every coordinate when absent).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

import numpy as np

from tpsr_ros.core.errors import DataError

__all__ = [
    "StateModel",
    "Track",
    "UpdateInfo",
    "check_actions",
    "check_observations",
    "planner_dim",
]


@dataclass(frozen=True)
class UpdateInfo:
    """Diagnostics of one state update.

    Attributes:
        normalizer: ``b_inf^T B_ao b`` for a TPSR (the model's prediction of the observation
            given the state, before the guard); ``nan`` for models without one (PCA).
        recovered: the update could not be normalised and the filter restarted (see
            :mod:`tpsr_ros.core.filtering`); a filter node counts these.

    """

    normalizer: float
    recovered: bool


class Track(NamedTuple):
    """States tracked over a trajectory of ``T`` steps, with per-step diagnostics.

    Attributes:
        states: ``(T, state_dim)``; row ``s`` is the state after step ``s``.
        normalizers: ``(T,)`` as :attr:`UpdateInfo.normalizer`.
        recovered: ``(T,)`` bool, as :attr:`UpdateInfo.recovered`.

    """

    states: np.ndarray
    normalizers: np.ndarray
    recovered: np.ndarray


@runtime_checkable
class StateModel(Protocol):
    """A fitted state representation: TPSR or a baseline."""

    method: ClassVar[str]
    """Short method name stored in model files: ``"tpsr"`` or ``"pca"``."""

    @property
    def state_dim(self) -> int:
        """Dimension of a state vector."""
        ...

    @property
    def n_actions(self) -> int:
        """Number of discrete actions; actions are indices ``0 .. n_actions - 1``."""
        ...

    @property
    def obs_size(self) -> int:
        """Length ``k`` of an observation vector."""
        ...

    def initial_state(self) -> np.ndarray:
        """State before any action-observation pair, ``(state_dim,)``."""
        ...

    def update(
        self, state: np.ndarray, action: int, observation: np.ndarray
    ) -> tuple[np.ndarray, UpdateInfo]:
        """Incorporate one pair: ``state (state_dim,)``, ``observation (obs_size,)``."""
        ...

    def track(
        self, actions: np.ndarray, observations: np.ndarray, initial: np.ndarray | None = None
    ) -> Track:
        """Track ``actions (T,)`` and ``observations (T, obs_size)`` from ``initial``.

        Equal to a loop of :meth:`update` starting at ``initial`` (default
        :meth:`initial_state`).
        """
        ...

    def parameters(self) -> dict[str, Any]:
        """Every parameter of the method, JSON-serialisable (stored in model files)."""
        ...

    def summary(self) -> dict[str, Any]:
        """Fit diagnostics, JSON-serialisable (singular values, explained variance, timing)."""
        ...

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the numeric content, for :mod:`tpsr_ros.io.model_io` (no object arrays)."""
        ...


def planner_dim(model: StateModel) -> int:
    """Leading state coordinates a planner sees: the model's ``planner_dim``, else all."""
    dim = getattr(model, "planner_dim", None)
    return int(model.state_dim if dim is None else dim)


def check_observations(observations: np.ndarray, obs_size: int) -> np.ndarray:
    """Observations ``(T, obs_size)`` as finite float64, or a ``DataError`` naming the problem."""
    obs = np.asarray(observations, dtype=np.float64)
    if obs.ndim != 2 or obs.shape[1] != obs_size:
        raise DataError(
            f"observations of shape {obs.shape} do not match the model's observation size "
            f"{obs_size}"
        )
    if not np.isfinite(obs).all():
        raise DataError("observations contain non-finite values (NaN or infinity)")
    return obs


def check_actions(actions: np.ndarray, n_actions: int, n_steps: int) -> np.ndarray:
    """``n_steps`` action indices in ``0 .. n_actions - 1`` as int64, or a ``DataError``."""
    arr = np.asarray(actions)
    if arr.shape != (n_steps,) or (arr.size and arr.dtype.kind not in "iu"):
        raise DataError(
            f"expected {n_steps} integer action indices, got {arr.dtype} array of shape {arr.shape}"
        )
    arr = arr.astype(np.int64, copy=False)
    if arr.size and (arr.min() < 0 or arr.max() >= n_actions):
        raise DataError(
            f"action indices must lie in 0..{n_actions - 1}, found {arr.min()}..{arr.max()}"
        )
    return arr
