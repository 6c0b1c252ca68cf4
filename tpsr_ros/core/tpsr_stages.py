"""The stages of a TPSR fit that every fit shares (guide Algorithms 1-3).

Whichever way the data arrive, in memory or in chunks, in one process or on a Dask
cluster (:mod:`tpsr_ros.core.tpsr`, :mod:`tpsr_ros.core.streamed_fit`), a fit runs these:
kernel centres (Algorithm 2), history/test and observation features, the compact rank-``r``
SVD of ``P_TH``, ``b_*`` and ``b_inf`` (eqs. 3.5, 3.6) and the per-action sums of eqs. 3.3
and 3.7, their pooling, and the checks on the way. One implementation of each means the
fits agree to rounding by construction.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import scipy.linalg
import scipy.sparse.linalg

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.features import CONSTANT_SCALE, rbf_features, select_centers
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.whitening import Whitening, flip_signs, single_blas_thread

__all__ = [
    "DENSE_SVD_LIMIT",
    "EXTRA_SINGULAR_VALUES",
    "SINGULAR_NOISE_FACTOR",
    "Progress",
    "Stopwatch",
    "action_operators",
    "action_sums",
    "as_actions",
    "centre_stride",
    "check_action_counts",
    "check_enough_episodes",
    "ht_features",
    "independent_episodes",
    "kernel_centres",
    "obs_features",
    "p_th_test_window",
    "p_th_window_actions",
    "pool_actions",
    "projected_outer",
    "rank_rule_refusal",
    "singular_value_floor",
    "start_and_normaliser",
    "supported_rank",
    "top_singular_triplets",
    "training_start",
    "truncated_svd",
    "whiten_test_window",
]

DENSE_SVD_LIMIT = 200
"""Matrices with a side at most this long get a full LAPACK SVD instead of ARPACK."""

EXTRA_SINGULAR_VALUES = 5
"""Singular values beyond the rank reported in the fit summary (to show the spectral gap)."""

SINGULAR_NOISE_FACTOR = 0.05
"""The rank rule's constant ``c``: a singular value of ``P_TH`` is supported by ``t``
training episodes when it is at least ``c / sqrt(t)`` of the largest (:func:`supported_rank`)."""

Progress = Callable[[str], None]


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


def as_actions(actions: np.ndarray, n_rows: int, n_actions: int) -> np.ndarray:
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


def p_th_window_actions(
    current: np.ndarray, test: np.ndarray | None, test_length: int
) -> np.ndarray | None:
    """Actions of Boots et al.'s ``P_TH`` test: the current one and ``n - 1`` test steps
    (None without the test steps' actions)."""
    if test is None:
        return None
    return np.concatenate([current[:, None], test[:, : test_length - 1]], axis=1)


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


def training_start(cfg: TPSRConfig) -> int:
    """The first training episode: 'first' kernel centres are the first episodes, which then
    do not train (t = |E| - max l); k-means centres are not taken out of the data."""
    return max(cfg.ht_centers, cfg.obs_centers) if cfg.center_selection == "first" else 0


def check_enough_episodes(n_episodes: int, cfg: TPSRConfig) -> None:
    """Refuse fewer episodes than the kernel centres (and, for 'first' ones, the rank) need."""
    n_centres = max(cfg.ht_centers, cfg.obs_centers)
    needed = training_start(cfg) + cfg.rank if cfg.center_selection == "first" else n_centres
    if n_episodes < needed:
        raise DataError(
            f"{n_episodes} episodes are too few for {n_centres} kernel centres: "
            f"'{cfg.center_selection}' centres with rank {cfg.rank} need at least {needed} "
            "(lower obs_centers/ht_centers or record more data)"
        )


def centre_stride(cfg: TPSRConfig, rows: int) -> int:
    """Kernel centres are chosen from one of every this many of the ``rows`` episodes
    (:func:`kernel_centres`): of overlapping ones every ``m + 1 + n``-th, or as many as
    the most centres asked for need (short data)."""
    if not cfg.overlapping_episodes:
        return 1
    needed = max(cfg.ht_centers, cfg.obs_centers, 1)
    return max(1, min(cfg.window_steps, rows // needed))


def kernel_centres(
    history: np.ndarray, test: np.ndarray, observation: np.ndarray, cfg: TPSRConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Algorithm 2, centres: ``l^H``, ``l^T`` and ``l^O`` of the whitened episodes' rows.

    Shared by the in-memory and the streamed fit, so both choose the same centres (the
    k-means seeds are ``seed``, ``seed + 1``, ``seed + 2``). Overlapping episodes are
    chosen from one episode in every ``m + 1 + n`` (the guide's non-overlapping ones):
    their neighbours are the same windows shifted by a step, and k-means on three times
    the rows would triple its cost for nearly the same centres. Data too short for that
    take them from more (:func:`centre_stride`).
    """
    select = cfg.center_selection
    step = centre_stride(cfg, history.shape[0])
    if step > 1:
        history, test, observation = history[::step], test[::step], observation[::step]
    return (
        select_centers(history, cfg.ht_centers, select, seed=cfg.seed, what="history"),
        select_centers(test, cfg.ht_centers, select, seed=cfg.seed + 1, what="test"),
        select_centers(observation, cfg.obs_centers, select, seed=cfg.seed + 2, what="observation"),
    )


def ht_features(rows: np.ndarray, centres: np.ndarray, cfg: TPSRConfig) -> np.ndarray:
    """History or test features of whitened ``rows``: ``(t, l + 1)`` with the constant feature."""
    return rbf_features(
        rows, centres, cfg.sigma_ht, normalize=cfg.normalize_ht_features, add_constant=True
    )


def obs_features(rows: np.ndarray, centres: np.ndarray, cfg: TPSRConfig) -> np.ndarray:
    """Normalised features of whitened current observations: ``(t, l_O)``."""
    return rbf_features(rows, centres, cfg.sigma_obs, normalize=True)


def truncated_svd(
    p_th: np.ndarray, cfg: TPSRConfig, *, refuse: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Algorithm 3's compact rank-``r`` SVD ``P_TH ~ U S V^T``.

    Returns ``U (l_T + 1, r)``, ``s (r,)``, ``V (l_H + 1, r)``, the singular values
    computed (``r`` plus :data:`EXTRA_SINGULAR_VALUES`, to show the gap) and how many of
    them are numerically non-zero; a rank above that is refused (unless ``refuse`` is
    False: the caller lowers the rank).
    """
    n_sv = min(cfg.rank + EXTRA_SINGULAR_VALUES, min(p_th.shape))
    u, s_all, v = top_singular_triplets(p_th, n_sv, seed=cfg.seed)
    tol = max(p_th.shape) * np.finfo(np.float64).eps * float(s_all[0])
    usable = int(np.count_nonzero(s_all > tol))
    if refuse and usable < cfg.rank:
        raise DataError(
            f"rank {cfg.rank} exceeds the {usable} usable singular values of P_TH (from "
            f"{s_all[0]:.3g} down to {s_all[min(cfg.rank, s_all.size) - 1]:.3g}); lower the rank "
            "or widen the history/test kernels"
        )
    r = cfg.rank
    return u[:, :r], s_all[:r], v[:, :r], s_all, usable


def independent_episodes(n_train: int, cfg: TPSRConfig) -> int:
    """How many of ``n_train`` training episodes share no step: all of the guide's, about
    one in every ``m + 1 + n`` of overlapping windows (a window at every step). The rank
    rule and the data's adequacy count these: a window shifted by a step adds one new image,
    not a new sample of the whole window."""
    return max(1, int(n_train) * cfg.episode_stride // cfg.window_steps) if n_train else 0


def singular_value_floor(largest: float, n_train: int) -> float:
    """The smallest singular value of ``P_TH`` that ``n_train`` training episodes support.

    ``P_TH`` is a mean of ``t`` outer products ``phi_T phi_H^T``; its sampling error has a
    spectral norm of order ``||phi_T phi_H^T|| / sqrt(t)`` (matrix concentration), and the
    largest singular value stands for that scale. A direction weaker than the error is
    noise, and the filter divides by it (``b_inf``, ``B_ao``: ``S^-1``), so it is dropped:
    the floor is ``largest * SINGULAR_NOISE_FACTOR / sqrt(t)``. The constant keeps every
    preset's rank on the simulator's data (3000-9000 steps: the smallest kept singular value
    lies at least 4 times above the floor) and drops the noise of a 20 s robot log.
    """
    return float(largest) * SINGULAR_NOISE_FACTOR / np.sqrt(max(int(n_train), 1))


def supported_rank(singular_values: np.ndarray, n_train: int, usable: int) -> int:
    """How many of ``singular_values`` (decreasing) reach :func:`singular_value_floor` and
    are among the ``usable`` numerically non-zero ones (at least 1)."""
    values = np.asarray(singular_values, dtype=np.float64)
    if values.size == 0:
        return 0
    floor = singular_value_floor(float(values[0]), n_train)
    return max(1, min(int(usable), int(np.count_nonzero(values >= floor))))


def rank_rule_refusal(rank: int, singular_values: np.ndarray, n_train: int, usable: int) -> str:
    """One line refusing a ``rank`` set on purpose above :func:`supported_rank`."""
    values = np.asarray(singular_values, dtype=np.float64)
    supported = supported_rank(values, n_train, usable)
    weakest = values[min(rank, values.size) - 1] / values[0]
    return (
        f"rank {rank} is above the {supported} singular value(s) of P_TH that {n_train} "
        f"training episodes support (at least {singular_value_floor(1.0, n_train):.2g} of the "
        f"largest; the {_ordinal(rank)} is {weakest:.2g} of it): set a rank of at most "
        f"{supported}, or record more data"
    )


def _ordinal(n: int) -> str:
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


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
