"""MergeBatch and MergeResult (mapmerge.result): what every method's merge returns."""

import numpy as np
import pytest

import mapmerge as mm
from mapmerge.result import MIN_MATCHED_LANDMARKS, MergeResult


def _batch(pairs_per_trial, B=3, n=12, seed=0):
    """build_batch of B random map pairs q = R p + t with the given correspondences of each."""
    from mapmerge.result import build_batch
    from mapmerge.triangles import triangulate_batches

    rng = np.random.default_rng(seed)
    P = rng.uniform(0, 10, (B, n, 2))
    theta = rng.uniform(-np.pi, np.pi, B)
    Q = mm.alignment.rotate(theta, P) + rng.uniform(-5, 5, (B, 1, 2))
    trial = np.repeat(np.arange(B), [len(p) for p in pairs_per_trial])
    pairs = np.concatenate([np.asarray(p, dtype=np.intp).reshape(-1, 2) for p in pairs_per_trial])
    tri_p, tri_q = triangulate_batches(P, Q)
    empty = np.zeros(0)
    return build_batch(method="paper", P=P, Q=Q, sigma=np.full(B, 0.1), log_tau=np.full(B, np.nan), tri_p=tri_p,
                       tri_q=tri_q, tri_trial=empty.astype(np.intp), triangle_pairs=np.zeros((0, 2), np.intp),
                       triangle_log_lr=empty, declared=empty.astype(bool), pair_trial=trial, pairs=pairs,
                       n_conflicts=np.zeros(B, np.int64)), theta


def test_fewer_than_three_correspondences_are_no_match():
    same = [(k, k) for k in range(MIN_MATCHED_LANDMARKS)]
    batch, theta = _batch([same, same[:2], []])
    assert batch.matched.tolist() == [True, False, False]
    assert batch.theta[0] == pytest.approx(theta[0])
    res = batch.result(1)
    assert isinstance(res, MergeResult) and not res.matched and res.alignment is None
    assert np.isnan(res.theta) and np.all(np.isnan(res.t))
    # No match: the combined map is map p alone, and the pairs found are still reported.
    np.testing.assert_array_equal(res.merged, batch.P[1])
    assert set(res.origin) == {"p"} and len(res.pairs) == 2


def test_a_result_holds_its_own_pairs_and_rows():
    batch, theta = _batch([[(0, 0), (1, 1), (2, 2), (3, 3)], [(5, 5), (6, 6), (7, 7)], [(1, 1), (2, 2), (9, 9)]])
    for b in range(3):
        res = batch.result(b)
        assert res.matched and res.theta == pytest.approx(theta[b])
        assert len(res.merged) == 2 * 12 - len(res.pairs)
        fused = res.origin == "fused"
        np.testing.assert_array_equal(np.sort(res.index_p[fused]), np.sort(res.pairs[:, 0]))
        # Exact maps: every fused landmark is its p estimate, every q-only one lands on its p twin.
        np.testing.assert_allclose(res.merged[fused], batch.P[b][res.index_p[fused]], atol=1e-9)
        only_q = res.origin == "q"
        np.testing.assert_allclose(res.merged[only_q], batch.P[b][res.index_q[only_q]], atol=1e-9)
        assert res.alignment.dof == 2 * len(res.pairs) - 3 and res.cov.shape == (len(res.merged), 2, 2)


def test_with_covariances_is_what_merge_maps_does_with_them():
    sc = mm.simulate.make_pair(60, 0.75, 30, rng=2, anisotropy=1.0)
    direct = mm.merge_maps(sc.p, sc.q, sc.sigma, cov_p=sc.cov_p, cov_q=sc.cov_q)
    batch = mm.merge_batch(sc.p[None], sc.q[None], sc.sigma, cov_p=sc.cov_p[None], cov_q=sc.cov_q[None])
    np.testing.assert_array_equal(batch.result(0).merged, direct.merged)
    np.testing.assert_array_equal(batch.result(0).cov, direct.cov)
