"""The combined map (mapmerge.combining): rows, provenance and covariances."""

import numpy as np

import mapmerge as mm


def test_combined_map_covariances():
    sc = mm.simulate.make_pair(60, 0.5, 35, rng=2)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus")
    cov = res.cov
    assert cov.shape == (len(res.merged), 2, 2)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    s2 = sc.sigma**2
    fused, only_p, only_q = (res.origin == o for o in ("fused", "p", "q"))
    np.testing.assert_allclose(cov[only_p], np.broadcast_to(s2 * np.eye(2), cov[only_p].shape))
    # Fused rows average two maps: close to σ²/2; mapped q rows add the fit's error.
    assert np.all(np.trace(cov[fused], axis1=1, axis2=2) < 1.5 * s2)
    assert np.all(np.trace(cov[only_q], axis1=1, axis2=2) > 2 * s2)


def test_information_weighted_fusion_matches_monte_carlo():
    """With per-landmark covariances, fused rows are the information-weighted mean and their
    covariance is the information sum's inverse, q's covariances rotated into p's frame."""
    from mapmerge.alignment import rotate
    from mapmerge.combining import combine_batch

    rng = np.random.default_rng(11)
    n, draws = 80, 4000
    world = rng.uniform(0, 20, (n, 2))
    theta, t = 0.7, np.array([3.0, -2.0])

    def spd(scale):
        a = rng.normal(size=(n, 2, 2)) * scale
        return a @ a.transpose(0, 2, 1) + 0.01 * scale**2 * np.eye(2)

    cov_p, cov_q = spd(0.05), spd(0.08)
    lp, lq = np.linalg.cholesky(cov_p), np.linalg.cholesky(cov_q)
    P = world + np.einsum("nij,bnj->bni", lp, rng.normal(size=(draws, n, 2)))
    Q = rotate(theta, world) + t + np.einsum("nij,bnj->bni", lq, rng.normal(size=(draws, n, 2)))
    trial = np.repeat(np.arange(draws), n)
    pairs = np.tile(np.stack([np.arange(n), np.arange(n)], axis=1), (draws, 1))
    # The true transform: this checks the fusion step; the row covariance leaves out the
    # fitted transform's own error (documented), which a fitted transform would add.
    th, tt = np.full(draws, theta), np.broadcast_to(t, (draws, 2))
    combined = combine_batch(P, Q, trial, pairs, np.ones(draws, bool), th, tt,
                             cov_p=np.broadcast_to(cov_p, (draws, n, 2, 2)),
                             cov_q=np.broadcast_to(cov_q, (draws, n, 2, 2)))
    fused = combined.points.reshape(draws, n, 2)
    predicted = combined.cov.reshape(draws, n, 2, 2).mean(axis=0)
    err = fused - world
    empirical = np.einsum("bni,bnj->nij", err, err) / draws
    ratio = np.trace(empirical, axis1=1, axis2=2) / np.trace(predicted, axis1=1, axis2=2)
    # 4,000 draws: each landmark's variance within 10 %.
    assert np.all(np.abs(ratio - 1) < 0.10), (ratio.min(), ratio.max())
    assert np.all(np.abs(err.mean(axis=0)) < 4 * np.sqrt(np.diagonal(predicted, axis1=1, axis2=2) / draws))
    # The fused estimate beats either map alone.
    assert np.all(np.trace(predicted, axis1=1, axis2=2) < np.trace(cov_p, axis1=1, axis2=2))
    # And merge_maps uses it: the same rows from one pair.
    res = mm.merge_maps(P[0], Q[0], 0.3, method="paper", cov_p=cov_p, cov_q=cov_q, tau=-20)
    fused_rows = res.origin == "fused"
    R = mm.rotation(res.theta)
    assert res.matched and np.allclose(res.cov[fused_rows], np.linalg.inv(
        np.linalg.inv(cov_p[res.index_p[fused_rows]]) + np.linalg.inv(
            np.einsum("ji,njk,kl->nil", R, cov_q[res.index_q[fused_rows]], R))))
