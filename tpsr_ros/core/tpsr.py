"""TPSR batch learning with RBF features: guide Algorithm 3 (section 3.2), eqs. 3.1-3.7.

From episodes (history, current action-observation pair, test; guide section 3.1) the fit

1. whitens histories, tests and current observations (Algorithm 1, :mod:`tpsr_ros.core.whitening`),
2. chooses kernel centres and computes the feature matrices (Algorithm 2,
   :mod:`tpsr_ros.core.features`): ``phi_H`` and ``phi_T`` with the constant feature, ``phi_O``
   normalised,
3. estimates ``P_H`` (eq. 3.1) and ``P_TH`` (eq. 3.2), normalised by ``1/t``,
4. takes the compact rank-``r`` SVD ``P_TH ~ U S V^T``,
5. computes ``b_* = S V^T e`` (eq. 3.5), ``b_inf^T = P_H^T V S^-1`` (eq. 3.6) and every
   ``B_ao' = U^T P_{T,ao',H} V S^-1`` (eqs. 3.3 and 3.7).

Step 5 never forms a ``(l_T + 1) x (l_H + 1)`` matrix per sample as line 14 of the literal
Algorithm 3 does. Since ``U^T phi_T phi_H^T V S^-1`` factorises, each sample is projected
first: ``A_T = phi_T U`` (``t x r``) and ``A_H = phi_H V S^-1`` (``t x r``), and for each
action ``a`` with samples ``Y_a``::

    B_a[o', :, :] = 1/t_a * sum_{i in Y_a} phi_O[i, o'] * outer(A_T[i], A_H[i])

is one ``(l_O x t_a) @ (t_a x r^2)`` matrix product. The cost is ``O(t (l_T + l_H) r +
t l_O r^2)`` instead of ``O(t l_T l_H l_O)``.

The SVD: ``P_TH`` is at most ``(l_T + 1) x (l_H + 1)`` and only its top singular triplets are
needed, so for matrices larger than :data:`DENSE_SVD_LIMIT` they come from Lanczos iteration
(``scipy.sparse.linalg.svds``, ARPACK, tolerance 0 = machine precision, fixed start vector);
smaller ones use a full LAPACK SVD. Signs follow ``svd_flip`` (largest entry of each left
singular vector positive), so fits are reproducible.

One choice the guide leaves implicit is exposed as :attr:`TPSRConfig.p_th_tests`: which
test window ``P_TH`` correlates with the history. The guide (eq. 3.2 with the same
``phi_T`` as eq. 3.3) uses the test *after* the current pair (``"after-current"``); Boots et
al. (2011) use the test *starting at* the current pair (``"from-current"``: the current
observation followed by the first ``n - 1`` test observations). Only the latter makes
``B_ao`` map a state to the state one step later under the same definition, so that
repeated updates stay exact; with the guide's choice one-step predictions from ``b_*`` are
exact but later updates carry a bias (``tests/test_tpsr_known_answer.py`` shows both).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, ClassVar, Literal, Protocol

import numpy as np
import scipy.linalg
import scipy.sparse.linalg

from tpsr_ros.core import filtering
from tpsr_ros.core.action_features import join_actions, standardised_codes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.features import CONSTANT_SCALE, rbf_features, select_centers
from tpsr_ros.core.fields import option as _param
from tpsr_ros.core.state_box import box_episodes, episode_states, state_box
from tpsr_ros.core.state_model import Track, UpdateInfo
from tpsr_ros.core.whitening import Whitening, check_finite_matrix, flip_signs, single_blas_thread

__all__ = [
    "DENSE_SVD_LIMIT",
    "TPSRConfig",
    "TPSRModel",
    "action_sums",
    "fit_tpsr",
    "fit_tpsr_episodes",
    "top_singular_triplets",
]

DENSE_SVD_LIMIT = 200
"""Matrices with a side at most this long get a full LAPACK SVD instead of ARPACK."""

EXTRA_SINGULAR_VALUES = 5
"""Singular values beyond the rank reported in the fit summary (to show the spectral gap)."""

Progress = Callable[[str], None]


_NUMBER_RULES: tuple[tuple[tuple[str, ...], Callable[[float], bool], str], ...] = (
    (("sigma_obs", "sigma_ht"), lambda v: np.isfinite(v) and v > 0, "a positive finite number"),
    (
        ("history_action_weight", "test_action_weight"),
        lambda v: np.isfinite(v) and v >= 0,
        "a non-negative finite number",
    ),
    (("state_clip_quantile",), lambda v: v == 0 or 0 < v < 0.5, "0 or in (0, 0.5)"),
    (("action_pooling",), lambda v: np.isfinite(v) and 0 <= v <= 1, "a number in [0, 1]"),
    (("obs_variance",), lambda v: v == 0 or 0 < v < 1, "0 or in (0, 1)"),
)
"""The real-valued parameters of :class:`TPSRConfig`: names, the rule, and how it reads."""


@dataclass(frozen=True)
class TPSRConfig:
    """Parameters of a TPSR fit (guide table 3.5); defaults: figure 4.5, rank 5 (section 4.3).

    History and test whitening dimensions, kernel centres and widths are coupled (``ht_*``),
    as in the guide's experiments.
    """

    history_length: int = _param(1, "m: observations per history (guide h/t-length)")
    test_length: int = _param(1, "n: observations per test (guide h/t-length)")
    obs_dim: int = _param(10, "d^O: dimensions kept when whitening current observations")
    obs_variance: float = _param(
        0.0,
        "keep instead the fewest d^O that explain this fraction of the current observations' "
        "variance (0: obs_dim, the guide; the fitted model's obs_dim records the d^O chosen)",
    )
    ht_dim: int = _param(10, "d^H = d^T: dimensions kept when whitening histories and tests")
    obs_centers: int = _param(500, "l^O: number of observation kernel centres")
    ht_centers: int = _param(1000, "l^H = l^T: number of history and test kernel centres")
    sigma_obs: float = _param(1.0, "sigma^O: kernel width of observation features")
    sigma_ht: float = _param(2.0, "sigma^H = sigma^T: kernel width of history/test features")
    rank: int = _param(5, "r: dimension of the TPSR state (singular values kept; guide dim)")
    center_selection: Literal["first", "kmeans"] = _param(
        "first",
        "kernel centres: the first episodes (guide) or k-means centroids",
        cli="--centers",
        choices=("first", "kmeans"),
    )
    normalize_ht_features: bool = _param(
        False, "normalise history/test features to sum 1 (Boots et al.; the guide does not)"
    )
    p_th_tests: Literal["after-current", "from-current"] = _param(
        "after-current",
        "test window of P_TH: after the current pair (guide eq. 3.2) or starting at it "
        "(Boots et al. 2011)",
        choices=("after-current", "from-current"),
    )
    history_action_weight: float = _param(
        0.0,
        "weight of each history step's action code joined to its observations before the "
        "RBF kernel (0: observations only, the guide; see tpsr_ros.core.action_features)",
    )
    test_action_weight: float = _param(
        0.0, "weight of each test step's action code joined to its observations (0: the guide)"
    )
    state_clip_quantile: float = _param(
        0.0,
        "clip every tracked state into the [q, 1 - q] quantiles of its training episodes' "
        "states (0: no clipping, the guide; see tpsr_ros.core.state_box)",
    )
    action_pooling: float = _param(
        0.0,
        "shrink each action's operators toward their mean over all actions by this fraction "
        "(0: one operator per action, the guide; 1: one for all; see pool_actions)",
    )
    seed: int = _param(0, "seed of k-means and of the SVD start vector")

    def __post_init__(self) -> None:
        for name in (
            "history_length",
            "test_length",
            "obs_dim",
            "ht_dim",
            "obs_centers",
            "ht_centers",
            "rank",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"{name} must be a positive integer, not {value!r}")
        for names, valid, rule in _NUMBER_RULES:
            for name in names:
                value = getattr(self, name)
                real = not isinstance(value, bool) and isinstance(value, (int, float, np.floating))
                if not (real and valid(value)):
                    raise ConfigError(f"{name} must be {rule}, not {value!r}")
        for f in fields(self):
            allowed = f.metadata.get("choices")
            if allowed is not None and getattr(self, f.name) not in allowed:
                raise ConfigError(
                    f"{f.name} must be one of {list(allowed)}, not {getattr(self, f.name)!r}"
                )
        if not isinstance(self.normalize_ht_features, bool):
            raise ConfigError(
                f"normalize_ht_features must be true or false, not {self.normalize_ht_features!r}"
            )
        if (
            isinstance(self.seed, bool)
            or not isinstance(self.seed, (int, np.integer))
            or self.seed < 0
        ):
            raise ConfigError(f"seed must be a non-negative integer, not {self.seed!r}")
        if self.rank > self.ht_centers + 1:
            raise ConfigError(
                f"rank {self.rank} exceeds the {self.ht_centers + 1} history/test features "
                "(ht_centers + 1)"
            )

    @property
    def uses_actions(self) -> bool:
        """Whether histories or tests carry action codes (:mod:`tpsr_ros.core.action_features`)."""
        return self.history_action_weight > 0 or self.test_action_weight > 0

    def to_dict(self) -> dict[str, Any]:
        """Parameters as a JSON-serialisable dict."""
        return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TPSRConfig:
        """Inverse of :meth:`to_dict`; unknown names are refused."""
        known = {f.name for f in fields(cls)}
        if unknown := sorted(set(values) - known):
            raise ConfigError(f"unknown TPSR parameters {unknown}")
        return cls(**values)


def top_singular_triplets(
    matrix: np.ndarray, k: int, *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compute the ``k`` largest singular triplets of ``matrix`` (``(p, q)``), exact to precision.

    Returns ``U (p, k)``, ``s (k,)`` in decreasing order and ``V (q, k)`` with deterministic
    signs. Uses ARPACK (``svds``, ``tol=0``) when the matrix exceeds :data:`DENSE_SVD_LIMIT`
    and ``k`` is small enough, else a full LAPACK SVD.
    """
    p, q = matrix.shape
    k = int(k)
    if not 1 <= k <= min(p, q):
        raise ConfigError(f"cannot take {k} singular values of a {p}x{q} matrix")
    if min(p, q) <= DENSE_SVD_LIMIT or k >= min(p, q) - 1:
        u, s, vt = scipy.linalg.svd(matrix, full_matrices=False)
        u, s, v = u[:, :k], s[:k], vt[:k].T
    else:
        v0 = np.random.default_rng(seed).uniform(0.5, 1.5, size=min(p, q))
        with single_blas_thread():  # ARPACK: many small matrix-vector products
            u, s, vt = scipy.sparse.linalg.svds(matrix, k=k, tol=0, v0=v0, solver="arpack")
        order = np.argsort(s)[::-1]
        u, s, v = u[:, order], s[order], vt[order].T
    u, v = flip_signs(u, v)
    return np.ascontiguousarray(u), s.copy(), np.ascontiguousarray(v)


def _as_actions(actions: np.ndarray, n_rows: int, n_actions: int) -> np.ndarray:
    arr = np.asarray(actions)
    if arr.shape != (n_rows,):
        raise DataError(f"expected {n_rows} actions, got an array of shape {arr.shape}")
    if arr.dtype.kind == "f":
        if not np.isfinite(arr).all() or not np.array_equal(arr, np.round(arr)):
            raise DataError("actions must be integer indices")
    elif arr.dtype.kind not in "iu":
        raise DataError(f"actions must be integer indices, not {arr.dtype}")
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= n_actions):
        raise DataError(
            f"action indices must lie in 0..{n_actions - 1}, found {arr.min()}..{arr.max()}"
        )
    return arr


@dataclass(frozen=True, eq=False)
class TPSRModel:
    """A learned TPSR (guide table 3.4) plus what Algorithm 4 needs to track states.

    Attributes:
        config: the parameters of the fit.
        obs_mean: ``(k,)`` whitening mean of current observations (``mean^O``).
        obs_whitening: ``(k, d_O)`` whitening matrix of current observations (``W^O``).
        obs_centers: ``(l_O, d_O)`` observation kernel centres (whitened).
        b_star: ``(r,)`` starting state ``b_*``.
        b_inf: ``(r,)`` normaliser ``b_inf``.
        B: ``(n_actions, l_O, r, r)``; ``B[a, o']`` is ``B_ao'``.
        singular_values: ``(>= r,)`` largest singular values of ``P_TH`` (first ``r`` kept).
        explained_variance: whitening explained-variance ratios, keys ``obs``, ``history``,
            ``test``, each ``(d,)``.
        fit_info: JSON-serialisable diagnostics (sample counts, timings in seconds).
        state_box: ``(2, r)`` low and high bound of every state coordinate, or None (no
            clipping); present exactly when ``config.state_clip_quantile > 0``.

    """

    method: ClassVar[str] = "tpsr"

    config: TPSRConfig
    obs_mean: np.ndarray
    obs_whitening: np.ndarray
    obs_centers: np.ndarray
    b_star: np.ndarray
    b_inf: np.ndarray
    B: np.ndarray
    singular_values: np.ndarray
    explained_variance: dict[str, np.ndarray]
    fit_info: dict[str, Any] = field(default_factory=dict)
    state_box: np.ndarray | None = None

    ARRAY_NAMES: ClassVar[tuple[str, ...]] = (
        "obs_mean",
        "obs_whitening",
        "obs_centers",
        "b_star",
        "b_inf",
        "B",
        "singular_values",
        "explained_variance_obs",
        "explained_variance_history",
        "explained_variance_test",
    )

    def __post_init__(self) -> None:
        r, k = self.config.rank, self.obs_mean.shape[0]
        d_o, l_o = self.config.obs_dim, self.config.obs_centers
        n_act = self.B.shape[0] if self.B.ndim == 4 and self.B.shape[0] >= 1 else "n_actions>=1"
        expected = {
            "obs_mean": (k,),
            "obs_whitening": (k, d_o),
            "obs_centers": (l_o, d_o),
            "b_star": (r,),
            "b_inf": (r,),
            "B": (n_act, l_o, r, r),
        }
        for name, shape in expected.items():
            arr = getattr(self, name)
            if arr.shape != shape:
                raise DataError(f"TPSR array {name} has shape {arr.shape}, expected {shape}")
        clipped = self.config.state_clip_quantile > 0
        if clipped != (self.state_box is not None):
            raise DataError(
                "TPSR state_box must be present exactly when state_clip_quantile > 0 "
                f"(state_clip_quantile {self.config.state_clip_quantile})"
            )
        if self.state_box is not None and (
            self.state_box.shape != (2, r) or not (self.state_box[0] <= self.state_box[1]).all()
        ):
            raise DataError(
                f"TPSR state_box has shape {self.state_box.shape} or low above high bounds, "
                f"expected (2, {r}) low <= high"
            )
        if self.singular_values.ndim != 1 or self.singular_values.shape[0] < r:
            raise DataError(
                f"TPSR singular_values has shape {self.singular_values.shape}, expected at "
                f"least {r} values"
            )

    # --- StateModel interface -------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        """TPSR dimension ``r``."""
        return int(self.config.rank)

    @property
    def n_actions(self) -> int:
        """Number of actions (first axis of ``B``)."""
        return int(self.B.shape[0])

    @property
    def obs_size(self) -> int:
        """Observation length ``k``."""
        return int(self.obs_mean.shape[0])

    def initial_state(self) -> np.ndarray:
        """``b_*`` (a copy)."""
        return np.array(self.b_star)

    def update(
        self, state: np.ndarray, action: int, observation: np.ndarray
    ) -> tuple[np.ndarray, UpdateInfo]:
        """Algorithm 4; see :func:`tpsr_ros.core.filtering.update`."""
        return filtering.update(self, state, action, observation)

    def track(
        self, actions: np.ndarray, observations: np.ndarray, initial: np.ndarray | None = None
    ) -> Track:
        """Algorithm 4 over a trajectory; see :func:`tpsr_ros.core.filtering.track`."""
        return filtering.track(self, actions, observations, initial)

    def parameters(self) -> dict[str, Any]:
        """Return the :class:`TPSRConfig` as a dict."""
        return self.config.to_dict()

    def summary(self) -> dict[str, Any]:
        """Singular values, whitening explained variance and fit diagnostics."""
        return {
            "singular_values": self.singular_values.tolist(),
            "explained_variance": {
                key: {"total": float(val.sum()), "per_dimension": val.tolist()}
                for key, val in self.explained_variance.items()
            },
            **self.fit_info,
        }

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Numeric content keyed by :attr:`ARRAY_NAMES`."""
        arrays = {
            name: getattr(self, name)
            for name in self.ARRAY_NAMES
            if not name.startswith("explained_variance_")
        }
        for key in ("obs", "history", "test"):
            arrays[f"explained_variance_{key}"] = self.explained_variance[key]
        if self.state_box is not None:
            arrays["state_box"] = self.state_box
        return arrays

    @classmethod
    def from_arrays(
        cls, arrays: dict[str, np.ndarray], parameters: dict[str, Any], summary: dict[str, Any]
    ) -> TPSRModel:
        """Rebuild a model from :meth:`to_arrays`, :meth:`parameters` and :meth:`summary`."""
        config = TPSRConfig.from_dict(parameters)
        info = {
            k: v for k, v in summary.items() if k not in ("singular_values", "explained_variance")
        }
        return cls(
            config=config,
            obs_mean=arrays["obs_mean"],
            obs_whitening=arrays["obs_whitening"],
            obs_centers=arrays["obs_centers"],
            b_star=arrays["b_star"],
            b_inf=arrays["b_inf"],
            B=arrays["B"],
            singular_values=arrays["singular_values"],
            explained_variance={
                key: arrays[f"explained_variance_{key}"] for key in ("obs", "history", "test")
            },
            fit_info=info,
            state_box=arrays.get("state_box"),
        )


class Stopwatch:
    """Records the duration of named stages and announces each one."""

    def __init__(self, progress: Progress | None) -> None:
        self.progress = progress
        self.timings: dict[str, float] = {}
        self._stage: str | None = None
        self._start = 0.0

    def stage(self, name: str) -> None:
        self.stop()
        if self.progress is not None:
            self.progress(name)
        self._stage, self._start = name, time.perf_counter()

    def stop(self) -> None:
        if self._stage is not None:
            self.timings[self._stage] = time.perf_counter() - self._start
            self._stage = None


def _check_data(
    history: np.ndarray,
    observation: np.ndarray,
    action: np.ndarray,
    test: np.ndarray,
    n_actions: int,
    cfg: TPSRConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validate the episodes (guide table 3.1) against the config: finite, shaped, enough."""
    observation = check_finite_matrix(observation, "current observations")
    n_episodes, k = observation.shape
    history = check_finite_matrix(history, "histories")
    test = check_finite_matrix(test, "tests")
    if history.shape != (n_episodes, cfg.history_length * k):
        raise DataError(
            f"histories have shape {history.shape}, expected ({n_episodes}, "
            f"{cfg.history_length} x {k}) for history_length {cfg.history_length}"
        )
    if test.shape != (n_episodes, cfg.test_length * k):
        raise DataError(
            f"tests have shape {test.shape}, expected ({n_episodes}, {cfg.test_length} x {k}) "
            f"for test_length {cfg.test_length}"
        )
    if int(n_actions) < 1:
        raise ConfigError(f"n_actions must be at least 1, not {n_actions}")
    action = _as_actions(action, n_episodes, int(n_actions))
    check_enough_episodes(n_episodes, cfg)
    return history, observation, action, test


@dataclass(frozen=True)
class _Whitened:
    """Algorithm 1's output: the fitted whitenings and the whitened episodes."""

    history: Whitening
    test: Whitening
    obs: Whitening
    h_white: np.ndarray
    t_white: np.ndarray
    o_white: np.ndarray
    t0_white: np.ndarray
    """Tests as ``P_TH`` correlates them (``t_white`` itself for ``after-current``)."""


@dataclass(frozen=True)
class StepActions:
    """The actions of the history and test steps, for action-aware features.

    ``history`` ``(E, m)`` and ``test`` ``(E, n)`` action indices (each step's action led to
    its observation), ``current`` ``(E,)`` and ``codes`` ``(n_actions, d)`` standardised
    action codes (:func:`tpsr_ros.core.action_features.standardised_codes`).
    """

    history: np.ndarray | None
    test: np.ndarray | None
    current: np.ndarray
    codes: np.ndarray

    def test_window(self, test_length: int) -> np.ndarray | None:
        """Actions of Boots et al.'s ``P_TH`` test: the current one and ``n - 1`` test steps."""
        if self.test is None:
            return None
        return np.concatenate([self.current[:, None], self.test[:, : test_length - 1]], axis=1)


def _whiten(
    history: np.ndarray,
    observation: np.ndarray,
    test: np.ndarray,
    cfg: TPSRConfig,
    actions: StepActions | None = None,
) -> _Whitened:
    """Algorithm 1: whiten histories, tests (``d^H = d^T``) and observations (``d^O``).

    With ``p_th_tests="from-current"`` the test window of ``P_TH`` (the current observation
    and the first ``n - 1`` test observations) is whitened with the tests' whitening. With
    action weights the whitened histories and tests get their steps' action codes joined
    (:func:`tpsr_ros.core.action_features.join_actions`).
    """
    wh_h, h_white = Whitening.fit_transform(history, cfg.ht_dim, what="histories")
    wh_t, t_white = Whitening.fit_transform(test, cfg.ht_dim, what="tests")
    wh_o, o_white = Whitening.fit_transform(
        observation, cfg.obs_dim, what="current observations", variance=cfg.obs_variance
    )
    if cfg.p_th_tests == "from-current":
        t0_white = whiten_test_window(wh_t, observation, test, cfg.test_length)
    else:
        t0_white = t_white
    if actions is not None and cfg.uses_actions:
        w_h, w_t = cfg.history_action_weight, cfg.test_action_weight
        h_white = join_actions(h_white, actions.history, actions.codes, w_h, "history")
        if t0_white is t_white:
            t_white = t0_white = join_actions(t_white, actions.test, actions.codes, w_t, "test")
        else:
            t_white = join_actions(t_white, actions.test, actions.codes, w_t, "test")
            window = actions.test_window(cfg.test_length)
            t0_white = join_actions(t0_white, window, actions.codes, w_t, "test")
    return _Whitened(wh_h, wh_t, wh_o, h_white, t_white, o_white, t0_white)


def p_th_test_window(observation: np.ndarray, test: np.ndarray, test_length: int) -> np.ndarray:
    """Boots et al.'s test of ``P_TH``: the current observation and ``n - 1`` test steps."""
    k = observation.shape[1]
    return np.concatenate([observation, test[:, : (test_length - 1) * k]], axis=1)


WINDOW_BLOCK_BYTES = 1 << 25
"""Rows of the ``P_TH`` test window are built and whitened in blocks of about 32 MiB."""


def whiten_test_window(
    whitening: Whitening, observation: np.ndarray, test: np.ndarray, test_length: int
) -> np.ndarray:
    """``whitening.transform(p_th_test_window(...))``, a block of rows at a time.

    The same values to rounding (bit-equal with OpenBLAS on the memory setting), without the
    two full-size temporaries of the one-shot version (the window and its centred copy:
    2 x 570 MB for tests of 8 images, whose first touch took 1.4 s of a 6-9 s fit).
    """
    n_rows = observation.shape[0]
    width = observation.shape[1] * test_length
    rows = max(1, WINDOW_BLOCK_BYTES // (8 * width))
    white = np.empty((n_rows, whitening.n_components))
    for start in range(0, n_rows, rows):
        block = slice(start, start + rows)
        white[block] = whitening.transform(
            p_th_test_window(observation[block], test[block], test_length)
        )
    return white


def check_enough_episodes(n_episodes: int, cfg: TPSRConfig) -> None:
    """Refuse fewer episodes than the kernel centres (and, for 'first' ones, the rank) need."""
    n_centres = max(cfg.ht_centers, cfg.obs_centers)
    # 'first' centres are taken out of the data (t = |E| - max l); k-means centres are not.
    needed = n_centres + cfg.rank if cfg.center_selection == "first" else n_centres
    if n_episodes < needed:
        raise DataError(
            f"{n_episodes} episodes are too few for {n_centres} kernel centres: "
            f"'{cfg.center_selection}' centres with rank {cfg.rank} need at least {needed} "
            "(lower obs_centers/ht_centers or record more data)"
        )


def kernel_centres(
    history: np.ndarray, test: np.ndarray, observation: np.ndarray, cfg: TPSRConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Algorithm 2, centres: ``l^H``, ``l^T`` and ``l^O`` of the whitened episodes' rows.

    Shared by the in-memory and the streamed fit, so both choose the same centres (the
    k-means seeds are ``seed``, ``seed + 1``, ``seed + 2``).
    """
    select = cfg.center_selection
    return (
        select_centers(history, cfg.ht_centers, select, seed=cfg.seed, what="history"),
        select_centers(test, cfg.ht_centers, select, seed=cfg.seed + 1, what="test"),
        select_centers(observation, cfg.obs_centers, select, seed=cfg.seed + 2, what="observation"),
    )


def _kernel_centres(
    white: _Whitened, cfg: TPSRConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, slice]:
    """The kernel centres and the training rows.

    'first' centres are the first episodes, which then do not train (``t = |E| - max l``).
    """
    centres = kernel_centres(white.h_white, white.t_white, white.o_white, cfg)
    n_centres = max(cfg.ht_centers, cfg.obs_centers)
    train = slice(n_centres, None) if cfg.center_selection == "first" else slice(None)
    return (*centres, train)


def _features(
    white: _Whitened,
    centres: tuple[np.ndarray, np.ndarray, np.ndarray],
    train: slice,
    cfg: TPSRConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Algorithm 2, features of the training episodes: ``phi_H``, ``phi_T``, ``phi_T0``, ``phi_O``.

    History and test features carry the constant feature; observation features are
    normalised to sum 1. ``phi_T0`` are the test features of ``P_TH`` (``phi_T`` unless
    ``from-current``).
    """
    c_h, c_t, c_o = centres
    phi_h = ht_features(white.h_white[train], c_h, cfg)
    phi_t = ht_features(white.t_white[train], c_t, cfg)
    if white.t0_white is white.t_white:
        phi_t0 = phi_t
    else:
        phi_t0 = ht_features(white.t0_white[train], c_t, cfg)
    phi_o = obs_features(white.o_white[train], c_o, cfg)
    return phi_h, phi_t, phi_t0, phi_o


def ht_features(rows: np.ndarray, centres: np.ndarray, cfg: TPSRConfig) -> np.ndarray:
    """History or test features of whitened ``rows``: ``(t, l + 1)`` with the constant feature."""
    return rbf_features(
        rows, centres, cfg.sigma_ht, normalize=cfg.normalize_ht_features, add_constant=True
    )


def obs_features(rows: np.ndarray, centres: np.ndarray, cfg: TPSRConfig) -> np.ndarray:
    """Normalised features of whitened current observations: ``(t, l_O)``."""
    return rbf_features(rows, centres, cfg.sigma_obs, normalize=True)


def _p_statistics(phi_h: np.ndarray, phi_t0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 3.1 and 3.2: ``P_H`` ``(l_H + 1,)`` and ``P_TH`` ``(l_T + 1, l_H + 1)``, over ``t``."""
    p_h = phi_h.mean(axis=0)  # eq. 3.1, (l_H + 1,)
    p_th = phi_t0.T @ phi_h  # eq. 3.2, (l_T + 1, l_H + 1)
    p_th /= phi_h.shape[0]
    return p_h, p_th


def truncated_svd(
    p_th: np.ndarray, cfg: TPSRConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Algorithm 3's compact rank-``r`` SVD ``P_TH ~ U S V^T``.

    Returns ``U (l_T + 1, r)``, ``s (r,)``, ``V (l_H + 1, r)``, the singular values
    computed (``r`` plus :data:`EXTRA_SINGULAR_VALUES`, to show the gap) and how many of
    them are numerically non-zero; a rank above that is refused.
    """
    n_sv = min(cfg.rank + EXTRA_SINGULAR_VALUES, min(p_th.shape))
    u, s_all, v = top_singular_triplets(p_th, n_sv, seed=cfg.seed)
    tol = max(p_th.shape) * np.finfo(np.float64).eps * float(s_all[0])
    usable = int(np.count_nonzero(s_all > tol))
    if usable < cfg.rank:
        raise DataError(
            f"rank {cfg.rank} exceeds the {usable} usable singular values of P_TH (largest "
            f"{s_all[: cfg.rank].tolist()}); lower the rank or widen the history/test kernels"
        )
    r = cfg.rank
    return u[:, :r], s_all[:r], v[:, :r], s_all, usable


def _parameters(
    p_h: np.ndarray,
    phi_h: np.ndarray,
    phi_t: np.ndarray,
    phi_o: np.ndarray,
    actions: np.ndarray,
    svd: tuple[np.ndarray, np.ndarray, np.ndarray],
    n_actions: int,
    pooling: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 3.5-3.7 (with 3.3): ``b_*``, ``b_inf`` and every ``B_ao'``; samples per action.

    ``pooling`` shrinks the per-action operators toward their pooled mean (:func:`pool_actions`).

    ``B_a[o'] = 1/t_a sum_{i in Y_a} phi_O[i, o'] outer(A_T[i], A_H[i])`` with
    ``A_T = phi_T U`` and ``A_H = phi_H V S^-1``: one matrix product per action (see the
    module docstring).
    """
    _, s, v = svd
    r = s.shape[0]
    b_star, b_inf = start_and_normaliser(p_h, s, v)
    outer = projected_outer(phi_h, phi_t, svd)
    counts = np.bincount(actions, minlength=n_actions)
    check_action_counts(counts)
    big_b = action_operators(action_sums(phi_o, outer, actions, counts), counts, pooling)
    return b_star, b_inf, big_b.reshape(n_actions, phi_o.shape[1], r, r), counts


def action_operators(sums: np.ndarray, counts: np.ndarray, pooling: float) -> np.ndarray:
    """Eq. 3.7: the per-action sums ``(n_actions, ...)`` over their counts, then pooled.

    Shared by the in-memory and the streamed fit; ``sums`` is divided in place.
    """
    sums /= counts.reshape(-1, *([1] * (sums.ndim - 1)))
    return pool_actions(sums, counts, pooling)


def pool_actions(operators: np.ndarray, counts: np.ndarray, weight: float) -> np.ndarray:
    """``B_a <- (1 - w) B_a + w B``, ``B`` the operators of all samples whatever their action.

    Each action's ``B_ao'`` is an average over the ``t_a`` training samples whose current
    action is ``a``, about a 25th of the data, so it is noisy; ``B = sum_a t_a B_a / t`` is
    the same average over every sample. Where the action that led to an observation tells
    little beyond the observation (a fully observable room), shrinking toward ``B`` trades
    that little for much less noise (measured in ``partial``, rank 8: one update from
    ``b_*`` locates the robot to 3.1 m with per-action operators, 1.1 m pooled; see
    docs/results.md). ``operators`` (``(n_actions, ...)``) are changed in place; ``w = 0``
    leaves them as they are (the guide).
    """
    if weight == 0:
        return operators
    pooled = np.tensordot(counts / counts.sum(), operators, axes=1)
    operators *= 1.0 - weight
    operators += weight * pooled
    return operators


def start_and_normaliser(
    p_h: np.ndarray, s: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 3.5 and 3.6: ``b_* = S V^T e`` (``e = (0, ..., 0, 1000)``), ``b_inf = P_H^T V S^-1``."""
    b_star = s * v[-1] * CONSTANT_SCALE
    b_inf = (p_h @ v) / s
    return b_star, b_inf


def projected_outer(
    phi_h: np.ndarray, phi_t: np.ndarray, svd: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> np.ndarray:
    """Per sample ``outer(U^T phi_T[i], S^-1 V^T phi_H[i])`` flattened: ``(t, r^2)``."""
    u, s, v = svd
    n_train, r = phi_h.shape[0], s.shape[0]
    a_t = phi_t @ u  # (t, r): U^T phi_T, transposed
    a_h = phi_h @ v
    a_h /= s  # (t, r): phi_H^T V S^-1
    return (a_t[:, :, None] * a_h[:, None, :]).reshape(n_train, r * r)


def check_action_counts(counts: np.ndarray) -> None:
    """Refuse an action that is never the current action of a training episode."""
    if (missing := np.flatnonzero(counts == 0)).size:
        raise DataError(
            f"action(s) {missing.tolist()} never occur as the current action of a training "
            "episode; record more data or check the action mapping"
        )


def action_sums(
    phi_o: np.ndarray, outer: np.ndarray, actions: np.ndarray, counts: np.ndarray
) -> np.ndarray:
    """Eqs. 3.3 and 3.7 unnormalised: ``sum_{i in Y_a} phi_O[i, o'] outer[i]`` per action.

    Returns ``(n_actions, l_O, r^2)``; one ``(l_O x t_a) @ (t_a x r^2)`` product per action
    (``counts`` = samples per action in ``actions``, which may be a block of the samples).
    """
    n_actions = counts.shape[0]
    sums = np.zeros((n_actions, phi_o.shape[1], outer.shape[1]))
    order = np.argsort(actions, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(counts)])
    for a in range(n_actions):
        if counts[a]:
            rows = order[bounds[a] : bounds[a + 1]]
            sums[a] = phi_o[rows].T @ outer[rows]
    return sums


def fit_tpsr(
    history: np.ndarray,
    observation: np.ndarray,
    action: np.ndarray,
    test: np.ndarray,
    *,
    n_actions: int,
    config: TPSRConfig | None = None,
    progress: Progress | None = None,
    history_actions: np.ndarray | None = None,
    test_actions: np.ndarray | None = None,
    action_codes: np.ndarray | None = None,
) -> TPSRModel:
    """Learn a TPSR from ``E`` episodes (guide Algorithms 1-3), one stage per step above.

    Args:
        history: ``(E, m k)`` observations of each history, oldest first, concatenated.
        observation: ``(E, k)`` current observation of each episode.
        action: ``(E,)`` current action indices in ``0 .. n_actions - 1``.
        test: ``(E, n k)`` observations of each test, concatenated.
        n_actions: number of actions; every action must occur among the training episodes.
        config: parameters (default :class:`TPSRConfig`).
        progress: called with the name of each stage as it starts.
        history_actions: ``(E, m)`` action of each history step (the one that led to its
            observation); needed only with ``history_action_weight > 0``.
        test_actions: ``(E, n)`` action of each test step; needed only with
            ``test_action_weight > 0``.
        action_codes: ``(n_actions, d)`` command of each action for action-aware features
            (default: the simulator's 25 velocity pairs).

    Raises:
        DataError: non-finite or inconsistent data, too few episodes for the kernel
            centres, rank above the usable singular values, an action without samples.
        ConfigError: action weights without the step actions or codes they need.

    """
    cfg = config if config is not None else TPSRConfig()
    watch = Stopwatch(progress)
    watch.stage("checking data")
    history, observation, action, test = _check_data(
        history, observation, action, test, n_actions, cfg
    )
    box_actions = _state_box_actions(history_actions, len(action), n_actions, cfg)
    step_actions = None
    if cfg.uses_actions:
        step_actions = StepActions(
            history_actions, test_actions, action, standardised_codes(action_codes, n_actions)
        )
    watch.stage("whitening")
    white = _whiten(history, observation, test, cfg, step_actions)
    watch.stage("kernel centres")
    c_h, c_t, c_o, train = _kernel_centres(white, cfg)
    watch.stage("features")
    phi_h, phi_t, phi_t0, phi_o = _features(white, (c_h, c_t, c_o), train, cfg)
    watch.stage("P-statistics")
    p_h, p_th = _p_statistics(phi_h, phi_t0)
    watch.stage("SVD")
    u, s, v, s_all, usable = truncated_svd(p_th, cfg)
    watch.stage("parameters")
    b_star, b_inf, big_b, counts = _parameters(
        p_h, phi_h, phi_t, phi_o, action[train], (u, s, v), int(n_actions), cfg.action_pooling
    )
    watch.stop()

    fit_info = {
        "episodes": int(observation.shape[0]),
        "training_episodes": int(phi_h.shape[0]),
        "samples_per_action": counts.tolist(),
        "usable_singular_values": usable,
        "timings": {name: round(sec, 6) for name, sec in watch.timings.items()},
    }
    unclipped = replace(cfg, state_clip_quantile=0.0)
    model = assemble_model(
        unclipped, (white.history, white.test, white.obs), c_o, (b_star, b_inf, big_b), s_all,
        fit_info,
    )
    if box_actions is None:
        return model
    watch = Stopwatch(progress)
    watch.stage("state box")
    rows = box_episodes(len(action))
    states = episode_states(
        model, history[rows], box_actions[rows], action[rows], observation[rows]
    )
    box = state_box(states, cfg.state_clip_quantile)
    watch.stop()
    model.fit_info["timings"].update({k: round(v, 6) for k, v in watch.timings.items()})
    clipped = replace(model.config, state_clip_quantile=cfg.state_clip_quantile)
    return replace(model, config=clipped, state_box=box)


def _state_box_actions(
    history_actions: np.ndarray | None, n_episodes: int, n_actions: int, cfg: TPSRConfig
) -> np.ndarray | None:
    """The history actions the state box is tracked with (checked before the fit), or None."""
    if cfg.state_clip_quantile == 0:
        return None
    if history_actions is None:
        raise ConfigError("state_clip_quantile > 0 needs the history actions of the episodes")
    acts = np.asarray(history_actions)
    if acts.shape != (n_episodes, cfg.history_length) or acts.dtype.kind not in "iu":
        raise DataError(
            f"history actions of shape {acts.shape} and dtype {acts.dtype} are not integer "
            f"indices of {n_episodes} episodes of {cfg.history_length} history steps"
        )
    if acts.size and (acts.min() < 0 or acts.max() >= n_actions):
        raise DataError(f"history action indices must lie in 0 .. {n_actions - 1}")
    return acts


def assemble_model(
    cfg: TPSRConfig,
    whitenings: tuple[Whitening, Whitening, Whitening],
    obs_centers: np.ndarray,
    parameters: tuple[np.ndarray, np.ndarray, np.ndarray],
    singular_values: np.ndarray,
    fit_info: dict[str, Any],
) -> TPSRModel:
    """The model of a fit (in memory or streamed): the observation whitening and centres,
    ``(b_*, b_inf, B)``, and the explained variance of the history, test and observation
    whitenings. Its config records the ``d^O`` the observation whitening kept."""
    history, test, obs = whitenings
    b_star, b_inf, big_b = parameters
    return TPSRModel(
        config=replace(cfg, obs_dim=obs.n_components),
        obs_mean=obs.mean_,
        obs_whitening=np.ascontiguousarray(obs.matrix_),
        obs_centers=obs_centers,
        b_star=b_star,
        b_inf=b_inf,
        B=big_b,
        singular_values=singular_values,
        explained_variance={
            "obs": obs.explained_variance_ratio_,
            "history": history.explained_variance_ratio_,
            "test": test.explained_variance_ratio_,
        },
        fit_info=fit_info,
    )


class EpisodeArrays(Protocol):
    """What :func:`fit_tpsr_episodes` reads (e.g. :class:`tpsr_ros.core.episodes.Episodes`)."""

    @property
    def history(self) -> np.ndarray: ...
    @property
    def observation(self) -> np.ndarray: ...
    @property
    def action(self) -> np.ndarray: ...
    @property
    def test(self) -> np.ndarray: ...
    @property
    def n_actions(self) -> int: ...
    @property
    def history_actions(self) -> np.ndarray: ...
    @property
    def test_actions(self) -> np.ndarray: ...


def fit_tpsr_episodes(
    episodes: EpisodeArrays,
    *,
    config: TPSRConfig | None = None,
    progress: Progress | None = None,
    action_codes: np.ndarray | None = None,
) -> TPSRModel:
    """:func:`fit_tpsr` on the arrays of cut episodes (``action_codes``: see there)."""
    return fit_tpsr(
        episodes.history,
        episodes.observation,
        episodes.action,
        episodes.test,
        n_actions=episodes.n_actions,
        config=config,
        progress=progress,
        history_actions=episodes.history_actions,
        test_actions=episodes.test_actions,
        action_codes=action_codes,
    )
