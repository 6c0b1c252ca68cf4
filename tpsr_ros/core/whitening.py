"""PCA whitening of observation data: guide Algorithm 1 (section 3.1).

``X_white = (X - mean^X) W^X`` with ``W^X = U diag(1 / sqrt(eigenvalues))``, keeping the ``d``
principal directions of largest variance, so the kept dimensions of the training data have
zero mean, unit variance and no covariance. The RBF kernel widths of the guide (table 3.5)
are expressed in these whitened units.

Implementation: the ``b x b`` sample covariance (``1 / (r - 1)``, the convention of
``numpy.cov``) is formed with one BLAS product and only its ``d`` largest eigenpairs are
computed (``scipy.linalg.eigh(subset_by_index=...)``), which is exact to numerical precision
and much cheaper than an SVD of the data. Wide data (``b > DENSE_MAX_DIM``, e.g. histories
of 4 images: 3072 values) never form the covariance: ARPACK's Lanczos iteration finds the
same ``d`` eigenpairs to machine precision (``tol=0``, a seeded start vector) from products
``X_c^T (X_c v)`` alone; forming and decomposing a 3072 x 3072 covariance took 7 s of the
guide's memory-experiment fit, the iteration about 1 s. Eigenvector signs are made deterministic as
scikit-learn's ``svd_flip`` does: the entry of largest magnitude of every direction is
positive. A direction whose eigenvalue is negligible
(at most ``max(r, b) * eps`` times the largest) would blow up under ``1 / sqrt``; asking
for more dimensions than the data's numerical rank is therefore refused with a ``DataError``.
:meth:`Whitening.from_moments` fits the same transform from merged
:class:`~tpsr_ros.core.moments.Moments` (mean and centred scatter gathered chunk by chunk,
the streamed fit's path), always through the dense covariance.

``variance`` in ``(0, 1)`` lets the data choose ``d``: the fewest leading directions whose
eigenvalues sum to that fraction of the total variance (scikit-learn's
``PCA(n_components=0.95)``), found from the eigenvalues of the dense covariance, or for wide
data from Lanczos runs of 16, 32, 64, ... directions until the fraction is reached.

Threads: LAPACK's symmetric eigensolver (and ARPACK, used by the TPSR fit) make thousands of
small level-2 BLAS calls; with a multithreaded OpenBLAS on a busy machine every call waits
for preempted threads, and a 0.03 s eigendecomposition was measured taking 5-15 s.
:func:`single_blas_thread` runs such calls on one BLAS thread (via ``threadpoolctl`` when
it is installed); the large matrix products keep every thread.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse.linalg

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.moments import Moments

__all__ = [
    "DENSE_MAX_DIM",
    "Whitening",
    "check_finite_matrix",
    "covariance_eigenpairs",
    "flip_signs",
    "single_blas_thread",
    "top_eigenpairs",
    "variance_eigenpairs",
]

DENSE_MAX_DIM = 1024


@contextlib.contextmanager
def single_blas_thread() -> Iterator[None]:
    """Limit BLAS to one thread inside the block (no-op without ``threadpoolctl``)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional dependency
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def check_finite_matrix(x: np.ndarray, what: str) -> np.ndarray:
    """Return ``x`` as a 2-D float64 array; refuse other ranks, emptiness and non-finite values."""
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2:
        raise DataError(f"{what} must be a 2-D array (samples x dimensions), got shape {arr.shape}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise DataError(f"{what} is empty (shape {arr.shape})")
    if not np.isfinite(arr).all():
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise DataError(f"{bad} non-finite values (NaN or infinity) in the {what}")
    return arr


def flip_signs(vectors: np.ndarray, other: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Make column signs deterministic: the largest-magnitude entry of each column is positive.

    ``vectors`` is ``(n, k)``; ``other`` (``(m, k)``, e.g. the right singular vectors) gets
    the same flips so that products such as ``U S V^T`` are unchanged.
    """
    idx = np.argmax(np.abs(vectors), axis=0)
    signs = np.sign(vectors[idx, np.arange(vectors.shape[1])])
    signs[signs == 0] = 1.0
    if other is None:
        return (vectors * signs,)
    return vectors * signs, other * signs


def covariance_eigenpairs(cov: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Return the ``d`` largest eigenpairs (ascending) of a covariance ``(b, b)`` and its trace."""
    b = cov.shape[0]
    with single_blas_thread():
        values, vectors = scipy.linalg.eigh(cov, subset_by_index=[b - d, b - 1])
    return values, vectors, float(np.trace(cov))


def top_eigenpairs(centred: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray, float]:
    """The ``d`` largest eigenpairs of the sample covariance of ``centred`` rows, and its trace.

    Eigenvalues come in ascending order, like ``scipy.linalg.eigh``. Narrow data use the
    dense covariance; wide data (more than :data:`DENSE_MAX_DIM` columns) a Lanczos
    iteration on the implicit covariance (see the module docstring).
    """
    n, b = centred.shape
    scale = 1.0 / (n - 1)
    if b <= DENSE_MAX_DIM or d >= b - 1:
        return covariance_eigenpairs(_covariance(centred), d)
    operator = scipy.sparse.linalg.LinearOperator(
        (b, b), matvec=lambda v: centred.T @ (centred @ v) * scale, dtype=np.float64
    )
    start = np.random.default_rng(0).standard_normal(b)
    values, vectors = scipy.sparse.linalg.eigsh(operator, k=d, which="LA", v0=start, tol=0)
    order = np.argsort(values)
    total = float(np.einsum("ij,ij->", centred, centred)) * scale
    return values[order], vectors[:, order], total


def _leading_dimensions(values: np.ndarray, total: float, fraction: float) -> int | None:
    """The fewest of the descending eigenvalues ``values`` that sum to ``fraction * total``,
    or None when all of them fall short."""
    reached = np.flatnonzero(np.cumsum(values) >= fraction * total)
    return int(reached[0]) + 1 if reached.size else None


def _check_fraction(fraction: float, what: str) -> None:
    if not 0 < fraction < 1:
        raise ConfigError(
            f"the variance kept when whitening {what} must lie in (0, 1), not {fraction}"
        )


def _covariance(centred: np.ndarray) -> np.ndarray:
    """The sample covariance ``(b, b)`` of ``centred`` rows (``1 / (r - 1)``), one BLAS product."""
    cov = centred.T @ centred
    cov *= 1.0 / (centred.shape[0] - 1)
    return cov


def variance_eigenpairs(
    centred: np.ndarray, fraction: float, what: str = "data"
) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`top_eigenpairs` for the fewest directions of ``centred`` rows
    that keep ``fraction`` of their variance, computed once: the dense covariance is formed
    one time, and the last Lanczos run's pairs are kept."""
    _check_fraction(fraction, what)
    b = centred.shape[1]
    if b <= DENSE_MAX_DIM:
        cov = _covariance(centred)
        return covariance_eigenpairs(cov, _covariance_dimensions(cov, fraction, what))
    k = 16
    while True:
        k = min(k, b - 1)
        values, vectors, total = top_eigenpairs(centred, k)
        found = _leading_dimensions(values[::-1], total, fraction)
        if found is not None:
            return values[-found:], vectors[:, -found:], total
        if k == b - 1:
            return top_eigenpairs(centred, b)
        k *= 2


def _covariance_dimensions(cov: np.ndarray, fraction: float, what: str = "data") -> int:
    """The fewest leading directions of a covariance ``(b, b)`` keeping ``fraction`` of its
    variance."""
    _check_fraction(fraction, what)
    with single_blas_thread():
        values = scipy.linalg.eigvalsh(cov)[::-1]
    total = float(np.trace(cov))
    if not total > 0:
        raise DataError(f"the {what} do not vary: no whitening dimension keeps any variance")
    found = _leading_dimensions(values, total, fraction)
    return found if found is not None else int(cov.shape[0])


def _check_dimensions(n: int, b: int, n_components: int, what: str) -> int:
    d = int(n_components)
    if d < 1:
        raise ConfigError(f"whitening of {what} must keep at least 1 dimension, not {d}")
    if d > b:
        raise ConfigError(f"whitening of {what} cannot keep {d} dimensions: the data have only {b}")
    if n < 2:
        raise DataError(f"whitening of {what} needs at least 2 data points, got {n}")
    return d


@dataclass(frozen=True, eq=False)
class Whitening:
    """A fitted whitening transform (Algorithm 1); build it with :meth:`fit`.

    Attributes:
        mean_: ``(b,)`` mean of the training rows (``mean^X``).
        components_: ``(b, d)`` orthonormal principal directions, largest variance first.
        eigenvalues_: ``(d,)`` variances along ``components_`` (sample covariance, ``1/(r-1)``).
        explained_variance_ratio_: ``(d,)`` each eigenvalue over the total variance.
        matrix_: ``(b, d)`` the whitening matrix ``W^X = components_ / sqrt(eigenvalues_)``.

    """

    mean_: np.ndarray
    components_: np.ndarray
    eigenvalues_: np.ndarray
    explained_variance_ratio_: np.ndarray

    @property
    def matrix_(self) -> np.ndarray:
        """The whitening matrix ``W^X``, ``(b, d)``."""
        matrix: np.ndarray = self.components_ / np.sqrt(self.eigenvalues_)
        return matrix

    @property
    def n_features_in(self) -> int:
        """Dimension ``b`` of the raw data."""
        return int(self.mean_.shape[0])

    @property
    def n_components(self) -> int:
        """Number ``d`` of kept (whitened) dimensions."""
        return int(self.eigenvalues_.shape[0])

    @classmethod
    def fit(
        cls, x: np.ndarray, n_components: int, *, what: str = "data", variance: float = 0.0
    ) -> Whitening:
        """Fit on ``x`` (``(r, b)``, one data point per row), keeping ``n_components`` dims.

        ``what`` names the data in error messages (e.g. ``"history observations"``). With
        ``variance`` in ``(0, 1)`` the dims kept are instead the fewest that keep that
        fraction of the variance (:func:`variance_eigenpairs`).
        """
        return cls._fit_centred(x, n_components, what, variance)[0]

    @classmethod
    def _fit_centred(
        cls, x: np.ndarray, n_components: int, what: str, variance: float = 0.0
    ) -> tuple[Whitening, np.ndarray]:
        """:meth:`fit`, also returning the centred rows ``x - mean`` it computed."""
        x = check_finite_matrix(x, what)
        n, b = x.shape
        d = _check_dimensions(n, b, 1 if variance else n_components, what)
        mean = x.mean(axis=0)
        centred = x - mean
        if variance:
            values, vectors, total = variance_eigenpairs(centred, variance, what)
        else:
            values, vectors, total = top_eigenpairs(centred, d)
        return cls._from_eigenpairs(mean, values, vectors, total, n, what), centred

    @classmethod
    def from_moments(
        cls, moments: Moments, n_components: int, *, what: str = "data", variance: float = 0.0
    ) -> Whitening:
        """Fit from merged :class:`~tpsr_ros.core.moments.Moments` (the streamed fit's path).

        Equal to :meth:`fit` on the rows up to rounding: the same covariance (``1 / (r - 1)``)
        and the same eigenpair, tolerance, sign and ``variance`` rules.
        """
        n, b = moments.count, moments.dim
        d = _check_dimensions(n, b, 1 if variance else n_components, what)
        if not (np.isfinite(moments.mean).all() and np.isfinite(moments.scatter).all()):
            raise DataError(f"non-finite values (NaN or infinity) in the {what}")
        cov = moments.scatter * (1.0 / (n - 1))
        if variance:
            d = _covariance_dimensions(cov, variance, what)
        values, vectors, total = covariance_eigenpairs(cov, d)
        return cls._from_eigenpairs(moments.mean.copy(), values, vectors, total, n, what)

    @classmethod
    def _from_eigenpairs(
        cls,
        mean: np.ndarray,
        values: np.ndarray,
        vectors: np.ndarray,
        total: float,
        n: int,
        what: str,
    ) -> Whitening:
        """Algorithm 1's lines 4-8 from ascending eigenpairs; refuse a rank-deficient ``d``."""
        b, d = vectors.shape
        values, vectors = values[::-1], vectors[:, ::-1]
        largest = float(values[0]) if values.size else 0.0
        tol = max(b, n) * np.finfo(np.float64).eps * max(largest, 0.0)
        usable = int(np.count_nonzero(values > tol)) if largest > 0 else 0
        if usable < d:
            raise DataError(
                f"whitening of {what} asks for {d} dimensions but the data have numerical rank "
                f"{usable} among their top {d} directions (eigenvalues from {largest:.3g} down "
                f"to {float(values[d - 1]) if d else 0.0:.3g}); lower the whitening dimension or "
                "provide more varied data"
            )
        (vectors,) = flip_signs(vectors)
        return cls(
            mean_=mean,
            components_=np.ascontiguousarray(vectors),
            eigenvalues_=values.copy(),
            explained_variance_ratio_=values / total,
        )

    def transform(self, x: np.ndarray) -> np.ndarray:
        """Whiten ``x``: ``(n, b) -> (n, d)``; a single row ``(b,)`` gives ``(d,)``."""
        arr = np.asarray(x, dtype=np.float64)
        if arr.shape[-1] != self.n_features_in:
            raise DataError(
                f"data of dimension {arr.shape[-1]} do not match the whitening fitted on "
                f"dimension {self.n_features_in}"
            )
        white: np.ndarray = (arr - self.mean_) @ self.matrix_
        return white

    @classmethod
    def fit_transform(
        cls, x: np.ndarray, n_components: int, *, what: str = "data", variance: float = 0.0
    ) -> tuple[Whitening, np.ndarray]:
        """Fit on ``x`` and return the transform with the whitened ``x`` (``(r, d)``).

        Equal, bit for bit, to ``fit`` then ``transform``, without centring ``x`` twice (a
        copy of the data: 570 MB for the tests of 8 images of the memory setting).
        """
        fitted, centred = cls._fit_centred(x, n_components, what, variance)
        white: np.ndarray = centred @ fitted.matrix_
        return fitted, white
