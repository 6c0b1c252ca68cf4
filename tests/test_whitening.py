"""Whitening (guide Algorithm 1): planted spectra, identity covariance, signs, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.whitening import Whitening


def planted(n: int = 4000, b: int = 30, seed: int = 0):
    """Data whose covariance has eigenvalues 100, 50, 20, 10, 5 and 0.01 for the rest."""
    rng = np.random.default_rng(seed)
    basis, _ = np.linalg.qr(rng.standard_normal((b, b)))
    variances = np.r_[100.0, 50.0, 20.0, 10.0, 5.0, np.full(b - 5, 0.01)]
    latent = rng.standard_normal((n, b))
    latent -= latent.mean(axis=0)
    # make the latent sample covariance exactly the identity, so the spectrum is exact
    cov = latent.T @ latent / (n - 1)
    latent = latent @ np.linalg.inv(np.linalg.cholesky(cov)).T
    x = (latent * np.sqrt(variances)) @ basis.T + rng.standard_normal(b) * 3
    return x, basis, variances


def test_planted_spectrum_and_directions_are_recovered():
    x, basis, variances = planted()
    w = Whitening.fit(x, 5)
    np.testing.assert_allclose(w.eigenvalues_, variances[:5], rtol=1e-10)
    np.testing.assert_allclose(
        w.explained_variance_ratio_, variances[:5] / variances.sum(), rtol=1e-10
    )
    # same directions up to sign
    np.testing.assert_allclose(np.abs(w.components_.T @ basis[:, :5]), np.eye(5), atol=1e-9)
    np.testing.assert_allclose(w.mean_, x.mean(axis=0), atol=1e-12)


def test_whitened_data_have_zero_mean_and_identity_covariance():
    x, _, _ = planted(seed=1)
    w, white = Whitening.fit_transform(x, 7)
    assert white.shape == (x.shape[0], 7)
    np.testing.assert_allclose(white.mean(axis=0), 0, atol=1e-10)
    np.testing.assert_allclose(np.cov(white, rowvar=False), np.eye(7), atol=1e-9)
    np.testing.assert_array_equal(white, w.transform(x))
    np.testing.assert_allclose(w.matrix_, w.components_ / np.sqrt(w.eigenvalues_))


def test_matches_the_literal_algorithm_with_numpy_pca():
    x, _, _ = planted(n=500, b=12, seed=2)
    centred = x - x.mean(axis=0)
    values, vectors = np.linalg.eigh(np.cov(centred, rowvar=False))
    values, vectors = values[::-1][:4], vectors[:, ::-1][:, :4]
    vectors *= np.sign(vectors[np.argmax(np.abs(vectors), axis=0), range(4)])
    literal = centred @ (vectors @ np.diag(1 / np.sqrt(values)))
    np.testing.assert_allclose(Whitening.fit(x, 4).transform(x), literal, atol=1e-9)


def test_signs_are_deterministic_and_independent_of_row_order():
    x, _, _ = planted(seed=3)
    a = Whitening.fit(x, 5)
    b = Whitening.fit(x[::-1].copy(), 5)
    idx = np.argmax(np.abs(a.components_), axis=0)
    assert (a.components_[idx, range(5)] > 0).all()
    np.testing.assert_allclose(a.components_, b.components_, atol=1e-10)


def test_single_row_transform():
    x, _, _ = planted(seed=4)
    w = Whitening.fit(x, 3)
    np.testing.assert_allclose(w.transform(x[5]), w.transform(x)[5], atol=1e-12)


def test_more_dimensions_than_the_data_rank_is_refused():
    rng = np.random.default_rng(5)
    x = rng.standard_normal((200, 3)) @ rng.standard_normal((3, 10))  # rank 3
    Whitening.fit(x, 3)
    with pytest.raises(DataError, match="numerical rank 3"):
        Whitening.fit(x, 4)
    with pytest.raises(DataError, match="numerical rank 0"):
        Whitening.fit(np.ones((50, 4)), 1)


@pytest.mark.parametrize("d", [0, 11])
def test_bad_dimension_counts(d):
    with pytest.raises(ConfigError):
        Whitening.fit(np.random.default_rng(0).standard_normal((50, 10)), d)


def test_non_finite_and_mismatched_data():
    x = np.random.default_rng(0).standard_normal((50, 4))
    x[3, 2] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        Whitening.fit(x, 2, what="histories")
    w = Whitening.fit(np.random.default_rng(0).standard_normal((50, 4)), 2)
    with pytest.raises(DataError, match="dimension 5"):
        w.transform(np.zeros((3, 5)))
    with pytest.raises(DataError, match="at least 2"):
        Whitening.fit(np.zeros((1, 4)), 1)


@pytest.mark.slow
def test_wide_data_take_the_lanczos_path_with_the_dense_result():
    # histories of several images are wider than DENSE_MAX_DIM: no covariance is formed,
    # and the eigenpairs agree with the dense eigendecomposition to machine precision
    from tpsr_ros.core import whitening

    rng = np.random.default_rng(4)
    b = whitening.DENSE_MAX_DIM + 200
    latent = rng.standard_normal((1500, 40)) * np.linspace(5.0, 1.0, 40)  # a decaying spectrum
    x = latent @ rng.standard_normal((40, b)) + 0.01 * rng.standard_normal((1500, b))
    wide = Whitening.fit(x, 12)
    centred = x - x.mean(axis=0)
    cov = centred.T @ centred / (len(x) - 1)
    values, vectors = np.linalg.eigh(cov)
    np.testing.assert_allclose(wide.eigenvalues_, values[::-1][:12], rtol=1e-10)
    np.testing.assert_allclose(wide.explained_variance_ratio_, values[::-1][:12] / values.sum(),
                               rtol=1e-10)
    expected = whitening.flip_signs(vectors[:, ::-1][:, :12])[0]
    np.testing.assert_allclose(wide.components_, expected, atol=1e-8)
    white = wide.transform(x)
    np.testing.assert_allclose(np.cov(white, rowvar=False), np.eye(12), atol=1e-8)


def test_fit_transform_equals_fit_then_transform_bit_for_bit():
    x, _, _ = planted(n=500, seed=3)
    fitted, white = Whitening.fit_transform(x, 4)
    np.testing.assert_array_equal(white, Whitening.fit(x, 4).transform(x))
    np.testing.assert_array_equal(white, fitted.transform(x))


@pytest.mark.parametrize(("fraction", "kept"), [(0.5, 1), (0.6, 2), (0.9, 3), (0.95, 4), (0.99, 5)])
def test_a_variance_fraction_keeps_the_fewest_directions_that_explain_it(fraction, kept):
    # the planted spectrum 100, 50, 20, 10, 5 and 25 x 0.01 (total 185.25): the leading
    # directions explain 54.0, 80.9, 91.7, 97.1 and 99.9 % of it
    x, _, _ = planted()
    by_variance = Whitening.fit(x, 1, variance=fraction)
    assert by_variance.n_components == kept
    np.testing.assert_array_equal(by_variance.matrix_, Whitening.fit(x, kept).matrix_)
    fitted, white = Whitening.fit_transform(x, 1, variance=fraction)
    np.testing.assert_array_equal(white, by_variance.transform(x))
    assert fitted.n_components == kept


@pytest.mark.slow
def test_the_variance_rule_from_moments_and_on_wide_data_agrees_with_the_dense_one():
    from tpsr_ros.core import whitening
    from tpsr_ros.core.moments import Moments

    x, _, _ = planted(n=600, seed=5)
    moments = Moments.of(x)
    assert Whitening.from_moments(moments, 1, variance=0.95).n_components == 4
    rng = np.random.default_rng(6)
    b = whitening.DENSE_MAX_DIM + 100
    latent = rng.standard_normal((1200, 60)) * np.linspace(6.0, 0.5, 60)
    wide = latent @ np.linalg.qr(rng.standard_normal((b, 60)))[0].T
    centred = wide - wide.mean(axis=0)
    values = np.linalg.eigvalsh(centred.T @ centred)[::-1]
    for fraction in (0.3, 0.8, 0.99):
        expected = int(np.searchsorted(np.cumsum(values) / values.sum(), fraction)) + 1
        assert expected > 1
        assert len(whitening.variance_eigenpairs(centred, fraction)[0]) == expected


@pytest.mark.parametrize("fraction", [1.0, 1.5, -0.1])
def test_a_variance_fraction_outside_zero_one_is_refused(fraction):
    x, _, _ = planted(n=100)
    with pytest.raises(ConfigError, match=r"must lie in \(0, 1\)"):
        Whitening.fit(x, 1, variance=fraction)


def test_constant_data_keep_no_variance():
    with pytest.raises(DataError, match="do not vary"):
        Whitening.fit(np.ones((50, 4)), 1, variance=0.9)
