"""RBF features (guide Algorithm 2) and kernel-centre selection."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.features import (
    CONSTANT_FEATURE,
    RBFFeatures,
    constant_vector,
    kmeans_plus_plus,
    rbf_features,
    select_centers,
)


def algorithm2_literal(centers, train, sigma, normalize, add_constant):
    """The guide's loops, returned as (t, l [+1]) rows."""
    out = []
    for xj in train:  # line 1
        total = 0.0
        row = []
        for ci in centers:  # line 3
            dist = float(np.sum((ci - xj) ** 2))
            act = np.exp(-dist / (2 * sigma**2))
            total += act
            row.append(act)
        if normalize:
            row = [v / total for v in row]
        if add_constant:
            row.append(1 / 1000)
        out.append(row)
    return np.array(out)


@pytest.mark.parametrize("normalize", [False, True])
@pytest.mark.parametrize("add_constant", [False, True])
@pytest.mark.parametrize("sigma", [0.7, 2.0])
def test_matches_the_literal_loops(normalize, add_constant, sigma):
    rng = np.random.default_rng(0)
    centers, train = rng.standard_normal((17, 4)), rng.standard_normal((23, 4))
    fast = rbf_features(train, centers, sigma, normalize=normalize, add_constant=add_constant)
    slow = algorithm2_literal(centers, train, sigma, normalize, add_constant)
    assert fast.shape == (23, 17 + add_constant)
    np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=1e-15)
    feature_map = RBFFeatures(centers, sigma, normalize, add_constant)
    np.testing.assert_array_equal(feature_map.transform(train), fast)
    assert feature_map.n_features == fast.shape[1]


def test_constant_vector_gives_ones():
    rng = np.random.default_rng(1)
    phi = rbf_features(
        rng.standard_normal((9, 3)), rng.standard_normal((5, 3)), 1.0, add_constant=True
    )
    assert (phi[:, -1] == CONSTANT_FEATURE).all()
    np.testing.assert_allclose(phi @ constant_vector(6), np.ones(9), rtol=1e-15)


@settings(max_examples=50, deadline=None)
@given(
    x=arrays(np.float64, (6, 3), elements=st.floats(-1e3, 1e3)),
    c=arrays(np.float64, (4, 3), elements=st.floats(-1e3, 1e3)),
    sigma=st.floats(0.01, 10.0),
)
def test_normalised_rows_sum_to_one_and_are_finite(x, c, sigma):
    phi = rbf_features(x, c, sigma, normalize=True)
    assert np.isfinite(phi).all()
    assert (phi >= 0).all()
    np.testing.assert_allclose(phi.sum(axis=1), 1.0, rtol=1e-12)


def test_far_from_every_centre_gives_the_nearest_centre_not_nan():
    centers = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    far = np.array([[1e4, 1.0], [-50.0, 1e4]])
    raw = rbf_features(far, centers, 0.5)
    assert (raw == 0).all()  # every activation underflows
    phi = rbf_features(far, centers, 0.5, normalize=True)
    np.testing.assert_array_equal(phi, [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    # equidistant from two centres: split evenly
    mid = rbf_features(
        np.array([[5.0, 1e4]]), np.array([[0.0, 0.0], [10.0, 0.0]]), 0.5, normalize=True
    )
    np.testing.assert_allclose(mid, [[0.5, 0.5]])


def test_distances_never_negative_for_duplicate_points():
    rng = np.random.default_rng(2)
    x = rng.standard_normal((50, 10)) * 1e3
    phi = rbf_features(x, x, 1.0)
    assert (phi <= 1.0).all()  # the clip at 0 keeps rounding from giving activations > 1
    # ||c||^2 + ||x||^2 - 2 x.c loses ~eps * ||x||^2 = 1e-9 here (whitened data have unit scale)
    np.testing.assert_allclose(np.diag(phi), 1.0, rtol=1e-7)


def test_rowwise_is_bitwise_batch_independent():
    rng = np.random.default_rng(3)
    x, c = rng.standard_normal((300, 10)), rng.standard_normal((200, 10))
    batch = rbf_features(x, c, 1.0, normalize=True, rowwise=True)
    for i in (0, 7, 299):
        np.testing.assert_array_equal(
            batch[i], rbf_features(x[i : i + 1], c, 1.0, normalize=True, rowwise=True)[0]
        )
    np.testing.assert_allclose(batch, rbf_features(x, c, 1.0, normalize=True), rtol=1e-12)


def test_center_selection():
    rng = np.random.default_rng(4)
    x = np.concatenate([rng.normal(m, 0.1, (100, 2)) for m in (-5, 0, 5)])
    rng.shuffle(x)
    np.testing.assert_array_equal(select_centers(x, 7, "first"), x[:7])
    a = select_centers(x, 3, "kmeans", seed=1)
    b = select_centers(x, 3, "kmeans", seed=1)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.sort(a[:, 0]), [-5, 0, 5], atol=0.1)


def test_kmeans_plus_plus_spreads_its_start_over_the_clusters():
    rng = np.random.default_rng(7)
    means = np.array([[-5.0, 0.0], [0.0, 5.0], [5.0, 0.0], [0.0, -5.0]])
    x = np.concatenate([rng.normal(m, 0.1, (50, 2)) for m in means])
    for seed in range(20):  # far clusters are ~2500 times likelier than the same one
        start = kmeans_plus_plus(x, 4, np.random.default_rng(seed))
        assert all(any(np.all(row == x, axis=1)) for row in start)  # rows of the data
        cluster = np.argmin(((start[:, None, :] - means) ** 2).sum(axis=2), axis=1)
        assert sorted(cluster) == [0, 1, 2, 3], seed
    same = kmeans_plus_plus(np.ones((5, 2)), 3, np.random.default_rng(0))  # all rows alike
    np.testing.assert_array_equal(same, np.ones((3, 2)))


def test_first_centres_read_only_the_first_rows():
    # the streamed fit takes them from a memory-mapped store: the rest is never read
    x = np.full((50, 3), np.nan)
    x[:7] = np.arange(21.0).reshape(7, 3)
    centres = select_centers(x, 7, "first")
    np.testing.assert_array_equal(centres, x[:7])
    assert not np.shares_memory(centres, x)
    with pytest.raises(DataError, match="non-finite values"):
        select_centers(x, 8, "first")
    with pytest.raises(DataError, match="non-finite values"):
        select_centers(x, 7, "kmeans")
    with pytest.raises(DataError, match="cannot choose 60 history kernel centres from only 50"):
        select_centers(np.zeros((50, 3)), 60, "first", what="history")


def test_bad_input():
    x = np.zeros((5, 2))
    with pytest.raises(ConfigError, match="sigma"):
        rbf_features(x, x, 0.0)
    with pytest.raises(DataError, match="do not match"):
        rbf_features(x, np.zeros((3, 3)), 1.0)
    with pytest.raises(DataError, match="only 5 episodes"):
        select_centers(x, 6)
    with pytest.raises(ConfigError):
        select_centers(x, 2, "random")
