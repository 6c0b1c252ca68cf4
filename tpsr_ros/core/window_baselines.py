"""Baselines that carry the past: stacked PCA frames and a finite-window predictive state.

The PCA baseline (:mod:`tpsr_ros.core.pca_baseline`) forgets everything but the current
image, so where two places look alike it cannot tell them apart; a TPSR can. To credit
the TPSR only with what a *recursive* state adds, it is compared with two states built
from a fixed window of the last ``k`` steps:

``stacked-pca`` (:class:`StackedPCAModel`), frame stacking as in the deep RL baselines
(Mnih et al. 2015): the step features ``x_t = [PCA(o_t), action(a_t)]`` (the PCA
baseline's projection of the image, same dimension rule, and the action that led to it)
of the last ``k`` steps, newest first, ``s_t = [x_t, x_{t-1}, ..., x_{t-k+1}]``. The state
*is* its window, so :meth:`~StackedPCAModel.update` shifts the new step in and drops the
oldest. Actions enter as the command's code by default (``actions="code"``: the velocity
``(v_x, v_y)`` of the simulator's action grid, 2 numbers, zero mean under uniform random
actions), not one-hot: 25 one-hot columns per step would outnumber the image's 2-4
components, and the planner's distances would be mostly about which command was sent.

``window`` (:class:`WindowModel`), the finite-window predictive state, Boots et al.
2011's fixed-length history baseline: the window ``w_t`` of the last ``k`` step features
(image components and one-hot actions: a linear map then gives each action its own
effect) is mapped by a ridge regression, fitted on the training trajectory, to the
features of the next :data:`FUTURE_STEPS` images (their top :data:`TARGET_COMPONENTS`
principal components weighted by the square root of their explained variance, as
:mod:`tpsr_ros.core.refine` does), and the state is the predicted future on its top
``dim`` principal directions: ``p_t = (w_t - mean) P``, a predictive state in units of
the predicted future (distances between states are distances between predictions).

Why the ``window`` state vector is longer than ``dim`` when ``k > 1``: ``update`` is
stateless, ``(state, a, o) -> state``, and ``p_{t+1}`` depends on the steps
``t-k+2 .. t`` that the ``dim`` numbers of ``p_t`` cannot give back. So the state vector is
``[p_t, x_t, ..., x_{t-k+2}]``: the predictive state, then a buffer of the newest
``k - 1`` step features for the next update (nothing for ``k = 1``, whose update ignores
the previous state). The buffer is memory for the update, not state for the planner:
:attr:`WindowModel.planner_dim` (``dim``) says how many leading coordinates the planner
sees, and :func:`tpsr_ros.core.fqi.ignore_trailing` turns a Q-function fitted on them
into one over the whole vector that gives the buffer zero weight. Letting the planner see
the buffer would make ``window`` a second ``stacked-pca``. The buffer is carried exactly
(copied, never reconstructed from ``p``), so :meth:`~WindowModel.track` equals a loop of
updates bit for bit.

Both models start from an empty window: steps before the first hold the training mean of
the step features (the mean image's components, zero, and the actions' mean features),
the expectation of a past not seen, in tracking, evaluation and the fit alike (every
training segment starts empty). Zeros would put one-hot actions where no real step
lies, and a planner would meet those states only at the start of each trial.

Neither model is saved to model files: they are experiment baselines (``learner
experiment --methods stacked-pca window``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.fields import check_positive_int, config_dict, config_from_dict, option
from tpsr_ros.core.refine import TARGET_COMPONENTS
from tpsr_ros.core.state_model import Track, UpdateInfo, check_actions, check_observations
from tpsr_ros.core.whitening import Whitening, flip_signs

__all__ = [
    "ACTION_FEATURES",
    "FUTURE_STEPS",
    "TARGET_COMPONENTS",
    "StackedPCAConfig",
    "StackedPCAModel",
    "WindowConfig",
    "WindowModel",
    "fit_stacked_pca",
    "fit_window",
    "window_rows",
]

ACTION_FEATURES = ("code", "one-hot")
"""How an action enters a step's features: the command's code, or one-hot."""

FUTURE_STEPS = 10
"""Future images the ``window`` regression predicts (as the predictive planner scaling)."""


def _check_actions_choice(value: Any, what: str) -> None:
    if value not in ACTION_FEATURES:
        raise ConfigError(f"{what} actions must be one of {list(ACTION_FEATURES)}, not {value!r}")


@dataclass(frozen=True)
class StackedPCAConfig:
    """Parameters of the stacked-PCA baseline."""

    k: int = option(2, "stacked PCA: steps in the window, the current one included")
    dim: int = option(3, "stacked PCA: principal components of each image")
    actions: Literal["code", "one-hot"] = option(
        "code",
        "stacked PCA: each step's action as the command's code or one-hot",
        choices=ACTION_FEATURES,
    )

    def __post_init__(self) -> None:
        check_positive_int(self.k, "stacked PCA k (steps in the window)")
        check_positive_int(self.dim, "stacked PCA dim (components of each image)")
        _check_actions_choice(self.actions, "stacked PCA")

    def to_dict(self) -> dict[str, Any]:
        """Parameters as a JSON-serialisable dict."""
        return config_dict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> StackedPCAConfig:
        """Inverse of :meth:`to_dict`; unknown names are refused."""
        return config_from_dict(cls, values, "stacked PCA")  # type: ignore[no-any-return]


@dataclass(frozen=True)
class WindowConfig:
    """Parameters of the finite-window predictive state."""

    k: int = option(2, "window: steps in the window, the current one included")
    dim: int = option(8, "window: state dimension (top directions of the predicted futures)")
    components: int = option(3, "window: principal components of each image in the window")
    actions: Literal["code", "one-hot"] = option(
        "one-hot",
        "window: each step's action as the command's code or one-hot",
        choices=ACTION_FEATURES,
    )
    ridge: float = option(
        1e-3, "window: ridge of the window-to-future regression, per sample, standardised units"
    )

    def __post_init__(self) -> None:
        check_positive_int(self.k, "window k (steps in the window)")
        check_positive_int(self.dim, "window dim (state dimension)")
        check_positive_int(self.components, "window components (of each image)")
        _check_actions_choice(self.actions, "window")
        ridge = self.ridge
        if isinstance(ridge, bool) or not isinstance(ridge, (int, float, np.floating)):
            raise ConfigError(f"window ridge must be a positive number, not {ridge!r}")
        if not (math.isfinite(ridge) and ridge > 0):
            raise ConfigError(f"window ridge must be a positive finite number, not {ridge!r}")

    def to_dict(self) -> dict[str, Any]:
        """Parameters as a JSON-serialisable dict."""
        return config_dict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> WindowConfig:
        """Inverse of :meth:`to_dict`; unknown names are refused."""
        return config_from_dict(cls, values, "window")  # type: ignore[no-any-return]


# --- step features and windows ---------------------------------------------------------


def _action_table(how: str, n_actions: int, action_codes: np.ndarray | None) -> np.ndarray:
    """``(n_actions, c)`` features of each action: the identity, or the commands' codes."""
    if n_actions < 1:
        raise DataError(f"a window baseline needs at least 1 action, not {n_actions}")
    if how == "one-hot":
        return np.eye(n_actions)
    if action_codes is None:
        raise ConfigError(
            "actions='code' needs the commands' codes (action_codes); use actions='one-hot' "
            "for data without them"
        )
    codes = np.asarray(action_codes, dtype=np.float64)
    if codes.ndim != 2 or codes.shape[0] != n_actions or not np.isfinite(codes).all():
        raise DataError(
            f"action codes must be a finite ({n_actions}, c) table, not shape {codes.shape}"
        )
    return codes.copy()


def _step_features(
    obs_mean: np.ndarray,
    obs_components: np.ndarray,
    table: np.ndarray,
    actions: np.ndarray,
    observations: np.ndarray,
) -> np.ndarray:
    """``(T, m)`` features ``[PCA(o_t), action(a_t)]``, row by row (stacked matmul) so that
    one update's row equals the batch's bit for bit."""
    codes = np.matmul((observations - obs_mean)[:, None, :], obs_components)[:, 0, :]
    return np.concatenate([codes, table[actions]], axis=1)


def window_rows(features: np.ndarray, k: int, history: np.ndarray | None = None) -> np.ndarray:
    """Windows ``(T, k * m)``: row ``t`` is ``[x_t, x_{t-1}, ..., x_{t-k+1}]``.

    ``history`` ``((k - 1) * m,)`` holds the steps before the first, newest first, as a
    state's buffer does (default zeros). Pure copies of the inputs.
    """
    n, m = features.shape
    before = np.zeros((k - 1) * m) if history is None else np.asarray(history, dtype=np.float64)
    if before.shape != ((k - 1) * m,):
        raise DataError(f"a window history of {(k - 1) * m} values is needed, not {before.shape}")
    padded = np.concatenate([before.reshape(k - 1, m)[::-1], features], axis=0)  # oldest first
    index = np.arange(n)[:, None] + (k - 1) - np.arange(k)[None, :]  # (T, k), newest first
    return padded[index].reshape(n, k * m)


def _segment_windows(
    features: np.ndarray, k: int, segments: np.ndarray | None, empty: np.ndarray
) -> np.ndarray:
    """Windows of every row, each segment starting from the empty window's history ``empty``."""
    if segments is None:
        return window_rows(features, k, empty)
    seg = np.asarray(segments)
    if seg.shape != (features.shape[0],):
        raise DataError(f"segments of shape {seg.shape} for {features.shape[0]} steps")
    cuts = np.flatnonzero(np.diff(seg)) + 1
    bounds = zip(np.r_[0, cuts], np.r_[cuts, features.shape[0]], strict=True)
    return np.concatenate([window_rows(features[a:b], k, empty) for a, b in bounds], axis=0)


def _check_pair(
    n_actions: int, obs_size: int, action: int, observation: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    actions = check_actions(np.asarray([action]), n_actions, 1)
    obs = check_observations(np.asarray(observation, dtype=np.float64)[None, :], obs_size)
    return actions, obs


def _check_state(state: np.ndarray, dim: int) -> np.ndarray:
    arr = np.asarray(state, dtype=np.float64)
    if arr.shape != (dim,):
        raise DataError(f"a state of {dim} values is needed, not shape {arr.shape}")
    return arr


# --- stacked PCA --------------------------------------------------------------------------


class _StepFeatures:
    """What both window models read of a step: its image's components and its action's
    features (``obs_mean``, ``obs_components`` and ``action_table`` of the model)."""

    obs_mean: np.ndarray
    obs_components: np.ndarray
    action_table: np.ndarray

    @property
    def step_dim(self) -> int:
        """Features of one step: image components plus action features."""
        return int(self.obs_components.shape[1] + self.action_table.shape[1])

    @property
    def n_actions(self) -> int:
        """Number of actions."""
        return int(self.action_table.shape[0])

    @property
    def obs_size(self) -> int:
        """Observation length."""
        return int(self.obs_mean.shape[0])

    def _features(self, actions: np.ndarray, observations: np.ndarray) -> np.ndarray:
        return _step_features(
            self.obs_mean, self.obs_components, self.action_table, actions, observations
        )


@dataclass(frozen=True, eq=False)
class StackedPCAModel(_StepFeatures):
    """A fitted stacked-PCA baseline: the state is the window of the last ``k`` steps.

    Attributes:
        config: the parameters.
        obs_mean: ``(b,)`` mean observation.
        obs_components: ``(b, dim)`` principal axes of the images.
        action_table: ``(n_actions, c)`` features of each action.
        padding: ``(m,)`` features of a step before the first (the training mean).
        explained_variance_ratio: ``(dim,)`` of the images' axes.
        fit_info: JSON-serialisable diagnostics.

    """

    method: ClassVar[str] = "stacked-pca"

    config: StackedPCAConfig
    obs_mean: np.ndarray
    obs_components: np.ndarray
    action_table: np.ndarray
    padding: np.ndarray
    explained_variance_ratio: np.ndarray
    fit_info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.padding.shape != (self.step_dim,):
            raise DataError(f"padding of shape {self.padding.shape}, not ({self.step_dim},)")

    @property
    def state_dim(self) -> int:
        """``k`` steps' features."""
        return int(self.config.k * self.step_dim)

    @property
    def planner_dim(self) -> int:
        """The planner sees the whole window."""
        return self.state_dim

    def initial_state(self) -> np.ndarray:
        """The empty window: ``k`` padding steps."""
        return np.tile(self.padding, self.config.k)

    def update(
        self, state: np.ndarray, action: int, observation: np.ndarray
    ) -> tuple[np.ndarray, UpdateInfo]:
        """Shift the new step's features in, drop the oldest step's."""
        previous = _check_state(state, self.state_dim)
        actions, obs = _check_pair(self.n_actions, self.obs_size, action, observation)
        new = self._features(actions, obs)[0]
        result = np.concatenate([new, previous[: self.state_dim - self.step_dim]])
        return result, UpdateInfo(normalizer=float("nan"), recovered=False)

    def track(
        self, actions: np.ndarray, observations: np.ndarray, initial: np.ndarray | None = None
    ) -> Track:
        """Windows over ``actions (T,)``, ``observations (T, b)`` from ``initial``."""
        obs = check_observations(observations, self.obs_size)
        acts = check_actions(actions, self.n_actions, obs.shape[0])
        start = self.initial_state() if initial is None else _check_state(initial, self.state_dim)
        history = start[: self.state_dim - self.step_dim]
        states = window_rows(self._features(acts, obs), self.config.k, history)
        n = states.shape[0]
        return Track(states, np.full(n, np.nan), np.zeros(n, dtype=bool))

    def parameters(self) -> dict[str, Any]:
        """The :class:`StackedPCAConfig` as a dict."""
        return self.config.to_dict()

    def summary(self) -> dict[str, Any]:
        """Explained variance of the images' axes and fit diagnostics."""
        ratio = self.explained_variance_ratio
        return {
            "explained_variance": {
                "obs": {"total": float(ratio.sum()), "per_dimension": ratio.tolist()}
            },
            **self.fit_info,
        }

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Numeric content (for the fingerprint a policy names)."""
        return {
            "obs_mean": self.obs_mean,
            "obs_components": self.obs_components,
            "action_table": self.action_table,
            "padding": self.padding,
            "explained_variance_ratio": self.explained_variance_ratio,
            "k": np.asarray(self.config.k, dtype=np.int64),
        }


def fit_stacked_pca(
    observations: np.ndarray,
    actions: np.ndarray,
    *,
    n_actions: int,
    config: StackedPCAConfig | None = None,
    action_codes: np.ndarray | None = None,
) -> StackedPCAModel:
    """Fit the images' PCA on ``observations (T, b)`` and the empty window's padding (the
    mean step features, with ``actions (T,)``); ``action_codes (n_actions, c)`` are the
    commands' codes, needed for ``actions="code"``."""
    cfg = config if config is not None else StackedPCAConfig()
    start = time.perf_counter()
    obs = check_observations(observations, np.asarray(observations).shape[-1])
    acts = check_actions(actions, n_actions, obs.shape[0])
    table = _action_table(cfg.actions, n_actions, action_codes)
    pca = Whitening.fit(obs, cfg.dim, what="observations")
    step = _step_features(pca.mean_, pca.components_, table, acts, obs)
    return StackedPCAModel(
        config=cfg,
        obs_mean=pca.mean_,
        obs_components=pca.components_,
        action_table=table,
        padding=step.mean(axis=0),
        explained_variance_ratio=pca.explained_variance_ratio_,
        fit_info={
            "steps": int(np.asarray(observations).shape[0]),
            "timings": {"PCA": round(time.perf_counter() - start, 6)},
        },
    )


# --- finite-window predictive state ------------------------------------------------------


@dataclass(frozen=True, eq=False)
class WindowModel(_StepFeatures):
    """A fitted finite-window predictive state: ``[p_t, buffer]`` (see the module's notes).

    Attributes:
        config: the parameters.
        obs_mean: ``(b,)`` mean observation.
        obs_components: ``(b, components)`` principal axes of the images in the window.
        action_table: ``(n_actions, c)`` features of each action.
        padding: ``(m,)`` features of a step before the first (the training mean).
        window_mean: ``(k * m,)`` mean window of the training steps.
        projection: ``(k * m, dim)`` window -> predicted future on its top directions.
        gains: ``(dim,)`` standard deviation of the training states along each direction.
        fit_info: JSON-serialisable diagnostics (variance of the future explained).

    """

    method: ClassVar[str] = "window"

    config: WindowConfig
    obs_mean: np.ndarray
    obs_components: np.ndarray
    action_table: np.ndarray
    padding: np.ndarray
    window_mean: np.ndarray
    projection: np.ndarray
    gains: np.ndarray
    fit_info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        width = self.config.k * self.step_dim
        if self.padding.shape != (self.step_dim,):
            raise DataError(f"padding of shape {self.padding.shape}, not ({self.step_dim},)")
        if self.window_mean.shape != (width,) or self.projection.shape != (
            width,
            self.config.dim,
        ):
            raise DataError(
                f"window arrays of shapes {self.window_mean.shape} and {self.projection.shape} "
                f"do not fit a window of {width} features and {self.config.dim} directions"
            )

    @property
    def buffer_dim(self) -> int:
        """Values of the buffer: the newest ``k - 1`` steps' features."""
        return int((self.config.k - 1) * self.step_dim)

    @property
    def planner_dim(self) -> int:
        """Leading coordinates the planner sees: the predictive state ``p_t``."""
        return int(self.config.dim)

    @property
    def state_dim(self) -> int:
        """``dim`` plus the buffer."""
        return self.planner_dim + self.buffer_dim

    def _states(self, windows: np.ndarray) -> np.ndarray:
        """``[p, buffer]`` of windows ``(T, k * m)``, row by row (bit-equal to one update)."""
        p = np.matmul((windows - self.window_mean)[:, None, :], self.projection)[:, 0, :]
        return np.concatenate([p, windows[:, : self.buffer_dim]], axis=1)

    def initial_state(self) -> np.ndarray:
        """The state of the empty window (``k`` padding steps): its prediction and buffer."""
        empty = np.tile(self.padding, self.config.k)[None, :]
        return self._states(empty)[0]

    def update(
        self, state: np.ndarray, action: int, observation: np.ndarray
    ) -> tuple[np.ndarray, UpdateInfo]:
        """The new window (the step, then the buffer) and its projection; ``p`` of the
        previous state is not used."""
        previous = _check_state(state, self.state_dim)
        actions, obs = _check_pair(self.n_actions, self.obs_size, action, observation)
        new = self._features(actions, obs)
        window = np.concatenate([new, previous[None, self.planner_dim :]], axis=1)
        return self._states(window)[0], UpdateInfo(normalizer=float("nan"), recovered=False)

    def track(
        self, actions: np.ndarray, observations: np.ndarray, initial: np.ndarray | None = None
    ) -> Track:
        """States over ``actions (T,)``, ``observations (T, b)`` from ``initial``."""
        obs = check_observations(observations, self.obs_size)
        acts = check_actions(actions, self.n_actions, obs.shape[0])
        start = self.initial_state() if initial is None else _check_state(initial, self.state_dim)
        windows = window_rows(self._features(acts, obs), self.config.k, start[self.planner_dim :])
        states = self._states(windows)
        n = states.shape[0]
        return Track(states, np.full(n, np.nan), np.zeros(n, dtype=bool))

    def predictive_states(self, states: np.ndarray) -> np.ndarray:
        """The planner's part ``p`` of states ``(T, state_dim)``."""
        return np.asarray(states)[..., : self.planner_dim]

    def parameters(self) -> dict[str, Any]:
        """The :class:`WindowConfig` as a dict."""
        return self.config.to_dict()

    def summary(self) -> dict[str, Any]:
        """Variance of the future explained by the regression and by the ``dim`` directions."""
        return dict(self.fit_info)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Numeric content (for the fingerprint a policy names)."""
        return {
            "obs_mean": self.obs_mean,
            "obs_components": self.obs_components,
            "action_table": self.action_table,
            "padding": self.padding,
            "window_mean": self.window_mean,
            "projection": self.projection,
            "gains": self.gains,
            "k": np.asarray(self.config.k, dtype=np.int64),
        }


def _future_features(observations: np.ndarray) -> np.ndarray:
    """``(T, q)`` top principal components of the images, each weighted by the square root
    of its explained variance (the targets of :mod:`tpsr_ros.core.refine`)."""
    kept = min(TARGET_COMPONENTS, observations.shape[1])
    pca = Whitening.fit(observations, kept, what="observations for the window's targets")
    white = (observations - pca.mean_) @ pca.matrix_
    weights = np.sqrt(np.maximum(pca.explained_variance_ratio_, 0.0))
    features: np.ndarray = white * weights
    return features


def _futures(
    features: np.ndarray, segments: np.ndarray | None, horizon: int
) -> tuple[np.ndarray, np.ndarray]:
    """Targets ``(T, horizon * q)`` (the features of steps ``t+1 .. t+horizon``) and the
    ``(T,)`` mask of rows whose future lies whole in their segment."""
    n = features.shape[0]
    seg = np.zeros(n, dtype=np.int64) if segments is None else np.asarray(segments)
    rows = np.arange(n)[:, None] + 1 + np.arange(horizon)[None, :]  # (T, horizon)
    inside = rows[:, -1] < n
    valid = np.zeros(n, dtype=bool)
    valid[inside] = seg[rows[inside, -1]] == seg[inside]
    targets = features[np.minimum(rows, n - 1)].reshape(n, -1)
    return targets, valid


def fit_window(
    observations: np.ndarray,
    actions: np.ndarray,
    *,
    n_actions: int,
    segments: np.ndarray | None = None,
    config: WindowConfig | None = None,
    action_codes: np.ndarray | None = None,
) -> WindowModel:
    """Fit the window predictive state on a training trajectory.

    ``observations (T, b)``, ``actions (T,)`` and ``segments (T,)`` (consecutive steps share
    a number; default one segment) are the training steps; ``action_codes`` are needed for
    ``actions="code"``. Steps whose :data:`FUTURE_STEPS` futures leave their segment are
    not regressed on. Raises ``DataError`` when ``dim`` exceeds what the window or the
    targets can span, or too few steps remain.
    """
    cfg = config if config is not None else WindowConfig()
    start = time.perf_counter()
    obs = check_observations(observations, np.asarray(observations).shape[-1])
    acts = check_actions(actions, n_actions, obs.shape[0])
    table = _action_table(cfg.actions, n_actions, action_codes)
    pca = Whitening.fit(obs, cfg.components, what="observations")
    step = _step_features(pca.mean_, pca.components_, table, acts, obs)
    padding = step.mean(axis=0)
    windows = _segment_windows(step, cfg.k, segments, np.tile(padding, cfg.k - 1))
    targets, valid = _futures(_future_features(obs), segments, FUTURE_STEPS)
    width, n_targets = windows.shape[1], targets.shape[1]
    if cfg.dim > min(width, n_targets):
        raise DataError(
            f"window dim {cfg.dim} exceeds what the regression can span: a window of "
            f"{width} features (k={cfg.k} steps of {step.shape[1]}) and {n_targets} targets"
        )
    x, y = windows[valid], targets[valid]
    if x.shape[0] <= width:
        raise DataError(
            f"the window regression needs more than {width} steps with {FUTURE_STEPS} future "
            f"steps in their segment; the data have {x.shape[0]}"
        )
    mean, y_mean = x.mean(axis=0), y.mean(axis=0)
    spread = x.std(axis=0)
    spread[spread < 1e-12 * max(float(spread.max()), 1e-300)] = 1.0  # a constant column
    z, y_c = (x - mean) / spread, y - y_mean
    gram = z.T @ z + cfg.ridge * z.shape[0] * np.eye(width)
    weights = np.linalg.solve(gram, z.T @ y_c)  # (width, horizon * q)
    predicted = z @ weights
    values, vectors = np.linalg.eigh(predicted.T @ predicted / (z.shape[0] - 1))
    order = np.argsort(values)[::-1][: cfg.dim]
    (directions,) = flip_signs(vectors[:, order])
    projection = (weights / spread[:, None]) @ directions  # (width, dim)
    total = float(np.sum(y_c**2))
    explained = 1.0 - float(np.sum((y_c - predicted) ** 2)) / max(total, 1e-300)
    top = np.clip(values[order], 0.0, None)
    return WindowModel(
        config=cfg,
        obs_mean=pca.mean_,
        obs_components=pca.components_,
        action_table=table,
        padding=padding,
        window_mean=mean,
        projection=projection,
        gains=np.sqrt(top),
        fit_info={
            "steps": int(obs.shape[0]),
            "regression_steps": int(x.shape[0]),
            "future_r2": round(explained, 6),
            "future_r2_top_dim": round(float(top.sum()) * (z.shape[0] - 1) / max(total, 1e-300), 6),
            "timings": {"fit": round(time.perf_counter() - start, 6)},
        },
    )
