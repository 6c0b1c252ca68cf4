"""Gaussian RBF kernel features: guide Algorithm 2 (section 3.1) and kernel-centre selection.

A feature is the activation ``exp(-||c_i - x||^2 / (2 sigma^2))`` of kernel centre ``c_i``
by a (whitened) data point ``x``. Unlike the guide's ``(l + 1) x t`` feature matrices (one
column per sample) the arrays here hold one row per sample, ``(t, l [+ 1])``: the transpose,
which keeps samples contiguous for BLAS.

- Squared distances are computed for all samples and centres at once as
  ``||c||^2 + ||x||^2 - 2 x . c`` (one matrix product), clipped at 0 against rounding.
- ``normalize`` divides each row by its sum over centres (kernel density weights, needed for
  current observations, eq. 3.9). The sum is computed after shifting every row by its
  smallest squared distance (the log-sum-exp trick): mathematically the same weights, but a
  point far from every centre, whose raw activations all underflow to 0, still gets finite
  weights that tend to a one-hot vector on its nearest centre(s) instead of ``0 / 0 = NaN``.
- ``add_constant`` appends the constant feature ``1 / 1000``; the matching vector ``e`` with
  ``(phi^H)^T e = 1`` has ``1000`` in its last entry (:func:`constant_vector`).

Kernel centres are the first ``l`` rows of the whitened data (the guide's default) or k-means
centroids (section 4.3): a k-means++ start (Arthur & Vassilvitskii 2007, seeded), then
scipy's ``kmeans2`` Lloyd iterations. The start is ours because scipy's own recomputes the
distances to every chosen centre for each new one, in a Python loop: 11 s for 1000 centres
over 5000 episodes (and an ``l x t`` distance matrix), where keeping each row's distance to
its nearest centre so far takes 0.2 s and ``t`` numbers.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial.distance import pdist

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.whitening import check_finite_matrix

__all__ = [
    "CONSTANT_FEATURE",
    "CONSTANT_SCALE",
    "KMEANS_ITERATIONS",
    "RBFFeatures",
    "constant_vector",
    "kmeans_plus_plus",
    "median_distance",
    "rbf_features",
    "select_centers",
    "squared_distances",
    "squared_norms",
]

CONSTANT_FEATURE = 1.0 / 1000.0
"""Value of the constant feature appended by ``add_constant`` (guide: 1/1000)."""
CONSTANT_SCALE = 1000.0
"""Last entry ``z`` of ``e``, so that ``CONSTANT_FEATURE * CONSTANT_SCALE == 1``."""

CenterSelection = Literal["first", "kmeans"]


def squared_norms(x: np.ndarray) -> np.ndarray:
    """Squared Euclidean norms ``(t,)`` of the rows of ``x`` (t, d), as
    :func:`squared_distances` computes them (so a stored copy gives the same bits)."""
    return np.einsum("ij,ij->i", x, x)


def squared_distances(
    x: np.ndarray,
    centers: np.ndarray,
    *,
    rowwise: bool = False,
    centers_sq: np.ndarray | None = None,
) -> np.ndarray:
    """Squared Euclidean distances ``(t, l)`` between rows of ``x`` (t, d) and ``centers`` (l, d).

    ``rowwise=True`` computes the products row by row (a stacked matmul, still one call):
    every row is then bitwise the same whatever the number of rows, which BLAS does not
    guarantee for a matrix product (it picks other kernels for a single row). The filter
    uses it so that batch tracking equals a loop of single updates exactly.
    ``centers_sq``: :func:`squared_norms` of ``centers`` computed once by a caller that
    reuses the centres (the filter, every step), else computed here.
    """
    x_sq = squared_norms(x)
    c_sq = squared_norms(centers) if centers_sq is None else centers_sq
    dist: np.ndarray
    if rowwise:
        dist = np.matmul(x[:, None, :], centers.T)[:, 0, :]
    else:
        dist = x @ centers.T
    dist *= -2.0
    dist += x_sq[:, None]
    dist += c_sq[None, :]
    np.maximum(dist, 0.0, out=dist)
    return dist


def rbf_features(
    x: np.ndarray,
    centers: np.ndarray,
    sigma: float,
    *,
    normalize: bool = False,
    add_constant: bool = False,
    rowwise: bool = False,
    centers_sq: np.ndarray | None = None,
) -> np.ndarray:
    """RBF feature matrix of ``x`` (``(t, d)``) for ``centers`` (``(l, d)``): ``(t, l [+ 1])``.

    Row ``j`` is the transposed column ``phi_{:, j}`` of the guide's Algorithm 2.
    ``rowwise`` and ``centers_sq``: see :func:`squared_distances`.
    """
    if not sigma > 0 or not np.isfinite(sigma):
        raise ConfigError(f"kernel width sigma must be a positive number, not {sigma}")
    x = np.asarray(x, dtype=np.float64)
    centers = np.asarray(centers, dtype=np.float64)
    if x.ndim != 2 or centers.ndim != 2 or x.shape[1] != centers.shape[1]:
        raise DataError(
            f"data of shape {x.shape} and kernel centres of shape {centers.shape} do not match"
        )
    dist = squared_distances(x, centers, rowwise=rowwise, centers_sq=centers_sq)
    if normalize and dist.shape[1] > 0:
        dist -= dist.min(axis=1, keepdims=True)
    dist *= -1.0 / (2.0 * float(sigma) ** 2)
    phi: np.ndarray = np.exp(dist, out=dist)
    if normalize and phi.shape[1] > 0:
        phi /= phi.sum(axis=1, keepdims=True)
    if add_constant:
        phi = np.concatenate([phi, np.full((phi.shape[0], 1), CONSTANT_FEATURE)], axis=1)
    return phi


def constant_vector(n_features: int) -> np.ndarray:
    """Return ``e`` (``(n_features,)``, zeros but ``CONSTANT_SCALE`` last), so ``phi e = 1``."""
    e = np.zeros(n_features)
    e[-1] = CONSTANT_SCALE
    return e


def median_distance(x: np.ndarray, *, max_points: int = 1000, seed: int = 0) -> float:
    """Median pairwise Euclidean distance of the rows of ``x`` (``(t, d)``): the usual
    data-driven RBF width (the "median heuristic").

    At most ``max_points`` rows, drawn without replacement by a generator seeded with
    ``seed``, enter the ``O(max_points^2)`` distances, so the cost is bounded on any data.
    """
    x = check_finite_matrix(x, "data for the median distance")
    if x.shape[0] < 2:
        raise DataError(f"the median distance needs at least 2 rows, got {x.shape[0]}")
    if x.shape[0] > max_points:
        rows = np.random.default_rng(seed).choice(x.shape[0], size=max_points, replace=False)
        x = x[np.sort(rows)]
    median = float(np.median(pdist(x)))
    if not median > 0:
        raise DataError("the median distance is 0: more than half of the rows are identical")
    return median


KMEANS_ITERATIONS = 20
"""Lloyd iterations of the k-means centres."""


def kmeans_plus_plus(x: np.ndarray, n_centers: int, rng: np.random.Generator) -> np.ndarray:
    """``n_centers`` rows of ``x`` ``(t, d)`` chosen by k-means++ seeding.

    The first row uniformly, every next one with probability proportional to its squared
    distance to the nearest row chosen so far (kept per row and updated once per centre:
    O(l t d) in all). Once every row coincides with a chosen one, the rest are uniform.
    """
    x = np.asarray(x, dtype=np.float64)
    chosen = np.empty(n_centers, dtype=np.int64)
    chosen[0] = rng.integers(len(x))
    nearest = np.sum((x - x[chosen[0]]) ** 2, axis=1)
    for i in range(1, n_centers):
        cumulative = np.cumsum(nearest)
        if cumulative[-1] > 0:
            pick = np.searchsorted(cumulative, rng.random() * cumulative[-1], side="right")
            chosen[i] = min(int(pick), len(x) - 1)
        else:
            chosen[i] = rng.integers(len(x))
        np.minimum(nearest, np.sum((x - x[chosen[i]]) ** 2, axis=1), out=nearest)
    return x[chosen].copy()


def select_centers(
    x: np.ndarray,
    n_centers: int,
    method: CenterSelection = "first",
    *,
    seed: int | None = 0,
    what: str = "data",
) -> np.ndarray:
    """Choose ``n_centers`` kernel centres ``(l, d)`` from whitened data ``x`` (``(t, d)``).

    ``"first"`` takes the first ``l`` rows (guide section 3.1); ``"kmeans"`` runs k-means
    (:func:`kmeans_plus_plus` seeded by ``seed``, then :data:`KMEANS_ITERATIONS` Lloyd
    iterations).
    """
    n_centers = int(n_centers)
    if n_centers < 1:
        raise ConfigError(
            f"the number of {what} kernel centres must be at least 1, not {n_centers}"
        )
    if method == "first":  # only these rows are read: a memory-mapped store stays on disk
        x = np.asarray(x)[:n_centers]
    x = check_finite_matrix(x, what)
    if n_centers > x.shape[0]:
        raise DataError(
            f"cannot choose {n_centers} {what} kernel centres from only {x.shape[0]} episodes"
        )
    if method == "first":
        return np.array(x)
    if method == "kmeans":
        start = kmeans_plus_plus(x, n_centers, np.random.default_rng(seed))
        with warnings.catch_warnings():
            # a cluster that loses all its rows keeps its centre, a data row: still a centre
            # on the data, nothing to warn about
            warnings.filterwarnings("ignore", "One of the clusters is empty", UserWarning)
            centroids, _ = kmeans2(x, start, iter=KMEANS_ITERATIONS, minit="matrix")
        return np.ascontiguousarray(centroids, dtype=np.float64)
    raise ConfigError(f"kernel centre selection {method!r} is not 'first' or 'kmeans'")


@dataclass(frozen=True, eq=False)
class RBFFeatures:
    """A feature map: kernel centres ``(l, d)`` with width and options (Algorithm 2)."""

    centers: np.ndarray
    sigma: float
    normalize: bool = False
    add_constant: bool = False

    @property
    def n_features(self) -> int:
        """Length of a feature vector: ``l`` (+ 1 with the constant feature)."""
        return int(self.centers.shape[0]) + int(self.add_constant)

    def transform(self, x: np.ndarray) -> np.ndarray:
        """Features of whitened ``x``: ``(t, d) -> (t, n_features)``."""
        return rbf_features(
            x, self.centers, self.sigma, normalize=self.normalize, add_constant=self.add_constant
        )
