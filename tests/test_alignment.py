"""Rigid motions, the n-point fit's helpers and outlier rejection (mapmerge.alignment)."""

import numpy as np
import pytest

import mapmerge as mm
from mapmerge.alignment import covariance_in_p_frame, mapped_covariance, reject_outliers, rotate


def test_wrap_angle_lands_in_the_half_open_interval():
    wrapped = mm.wrap_angle(np.array([np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 0.5, 7.0]))
    assert np.all((wrapped > -np.pi) & (wrapped <= np.pi))
    np.testing.assert_allclose(wrapped[:4], np.pi)
    assert wrapped[5] == pytest.approx(7.0 - 2 * np.pi)


def test_rotate_and_rotation_agree_and_compose():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 2))
    a, b = 0.3, -1.1
    np.testing.assert_allclose(rotate(a, x), x @ mm.rotation(a).T)
    np.testing.assert_allclose(rotate(a, rotate(b, x)), rotate(a + b, x), atol=1e-15)
    cov = np.array([[[2.0, 0.3], [0.3, 1.0]]])
    R = mm.rotation(a)
    np.testing.assert_allclose(covariance_in_p_frame(a, cov)[0], R.T @ cov[0] @ R)


def test_reject_outliers_drops_a_planted_outlier_only():
    rng = np.random.default_rng(1)
    P = rng.uniform(0, 10, (20, 2))
    Q = rotate(0.7, P) + [3.0, -2.0] + rng.normal(0, 0.05, P.shape)
    Q[4] += [2.0, 1.0]
    pairs = np.stack([np.arange(20), np.arange(20)], axis=1)
    kept = reject_outliers(P, Q, pairs, 0.05)
    assert 4 not in kept[:, 0] and len(kept) >= 18


def test_mapped_covariance_matches_monte_carlo():
    rng = np.random.default_rng(2)
    theta, t = 0.4, np.array([1.0, -2.0])
    cov_tt = np.diag([1e-4, 4e-4, 9e-4])
    own = 0.01**2
    x_true = np.array([[5.0, 3.0]])
    q = rotate(theta, x_true) + t
    draws = rng.multivariate_normal(np.concatenate([[theta], t]), cov_tt, 20000)
    noisy_q = q + rng.normal(0, 0.01, (20000, 2))
    x = np.stack([rotate(-d[0], (nq - d[1:])[None])[0] for d, nq in zip(draws, noisy_q)])
    predicted = mapped_covariance(x_true, theta, cov_tt, own)[0]
    np.testing.assert_allclose(np.cov(x.T), predicted, rtol=0.05, atol=1e-7)


def test_fit_matched_fits_the_map_pairs_with_enough_correspondences_and_nan_the_rest():
    from mapmerge.alignment import fit_matched, fit_transforms

    rng = np.random.default_rng(4)
    P = rng.uniform(0, 10, (3, 8, 2))
    Q = rotate(np.array([0.2, -1.0, 2.5]), P) + rng.normal(0, 0.01, (3, 8, 2))
    pair_trial = np.array([0, 0, 0, 0, 1, 1])
    pairs = np.array([[0, 0], [1, 1], [2, 2], [5, 5], [3, 3], [4, 4]])
    matched, theta, t, cost = fit_matched(P, Q, pair_trial, pairs, 3)
    assert matched.tolist() == [True, False, False]
    alone = fit_transforms(np.zeros(4, np.intp), P[0, pairs[:4, 0]], Q[0, pairs[:4, 1]], 1)
    assert theta[0] == alone[0][0] and np.array_equal(t[0], alone[1][0]) and cost[0] == alone[2][0]
    assert abs(theta[0] - 0.2) < 0.01
    assert np.isnan(theta[1:]).all() and np.isnan(t[1:]).all() and np.isnan(cost[1:]).all()
