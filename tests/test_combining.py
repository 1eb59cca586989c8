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
