"""The sparse large-map path agrees with the dense one; the gate is complete."""

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import matching, metrics
from mapmerge.matching import gate_radius, side_features

from lp_reference import lapjvsp_assign

LOG_TAU = mm.resolve_log_tau("chi2:0.01")


def match_triangles(P, Q, sigma, objective, cyclic=False, log_tau=None, sparse=None):
    """The driver on one map pair (its batch of one)."""
    return matching.match_triangles(P[None], Q[None], np.array([sigma]), objective, cyclic, log_tau, sparse)


def _declared(match):
    keep = match.log_lr >= LOG_TAU
    return match.triangle_pairs[keep], match.log_lr[keep]


def test_gate_radius_bounds_every_declarable_pair(rng):
    sc = mm.simulate.make_pair(150, 0.75, 25, rng=4)
    tp, tq = mm.triangulate(sc.p).coords, mm.triangulate(sc.q).coords
    for cyclic in (False, True):
        L = mm.glrt(tp, tq, sc.sigma, cyclic=cyclic)
        i, j = np.nonzero(L >= LOG_TAU)
        dist = np.linalg.norm(side_features(tp)[i] - side_features(tq)[j], axis=1)
        assert dist.max() <= gate_radius(sc.sigma, LOG_TAU)


@pytest.mark.parametrize("n, snr, cyclic", [(400, 40, False), (400, 40, True), (200, 30, True)])
def test_sparse_declares_what_dense_declares(monkeypatch, n, snr, cyclic):
    # A cap above the gate's crowding makes the sparse candidate set complete.
    monkeypatch.setattr(matching, "SPARSE_NEIGHBOURS", 256)
    sc = mm.simulate.make_pair(n, 0.75, snr, rng=3)
    dense = match_triangles(sc.p, sc.q, sc.sigma, "lr", cyclic, LOG_TAU, sparse=False)
    sparse = match_triangles(sc.p, sc.q, sc.sigma, "lr", cyclic, LOG_TAU, sparse=True)
    (dp, ds), (sp, ss) = _declared(dense), _declared(sparse)
    np.testing.assert_array_equal(dp, sp)
    np.testing.assert_allclose(ds, ss, rtol=1e-9, atol=1e-9)


def test_default_cap_agrees_at_high_snr():
    sc = mm.simulate.make_pair(400, 0.75, 40, rng=5)
    dense = match_triangles(sc.p, sc.q, sc.sigma, "lr", False, LOG_TAU, sparse=False)
    sparse = match_triangles(sc.p, sc.q, sc.sigma, "lr", False, LOG_TAU, sparse=True)
    np.testing.assert_array_equal(_declared(dense)[0], _declared(sparse)[0])


def test_merge_maps_switches_to_sparse_and_gives_the_dense_merge(monkeypatch):
    sc = mm.simulate.make_pair(400, 0.75, 40, rng=6)
    auto = mm.merge_maps(sc.p, sc.q, sc.sigma, method="paper")  # Tp·Tq > DENSE_MAX_PAIRS
    assert len(auto.tri_p) * len(auto.tri_q) > matching.DENSE_MAX_PAIRS
    monkeypatch.setattr(matching, "DENSE_MAX_PAIRS", 10**12)
    dense = mm.merge_maps(sc.p, sc.q, sc.sigma, method="paper")
    np.testing.assert_array_equal(auto.pairs, dense.pairs)
    np.testing.assert_allclose(auto.merged, dense.merged, atol=1e-12)


def test_sparse_path_needs_a_finite_threshold():
    sc = mm.simulate.make_pair(30, 0.75, 40, rng=1)
    with pytest.raises(ValueError, match="finite threshold"):
        match_triangles(sc.p, sc.q, sc.sigma, "lr", sparse=True, log_tau=-np.inf)


def test_consensus_on_a_large_map_uses_the_hough_pool():
    sc = mm.simulate.make_pair(3000, 0.75, 30, rng=2)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus")
    err = metrics.map_errors(sc, res)
    assert err["success"] and err["correct_pairs"] > 0.95 * sc.n_common
    assert err["wrong_pairs"] < 0.01 * sc.n_common


def test_consensus_large_unrelated_maps_give_no_match():
    sc = mm.simulate.make_pair(3000, 0.75, 30, rng=3, unrelated=True)
    assert not mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus").matched


@pytest.mark.parametrize("method, seed", [("paper", 100), ("paper", 101), ("cyclic", 102)])
def test_min_cost_flow_merges_as_scipys_sparse_assignment(monkeypatch, method, seed):
    """Whole merges on the sparse path (400 landmarks, 25 dB: many competing candidates)."""
    sc = mm.simulate.make_pair(400, 0.75, 25, rng=seed)
    flow = mm.merge_maps(sc.p, sc.q, sc.sigma, method=method)
    monkeypatch.setattr(matching, "assign_sparse", lapjvsp_assign)
    lapjvsp = mm.merge_maps(sc.p, sc.q, sc.sigma, method=method)
    np.testing.assert_array_equal(flow.triangle_pairs[flow.declared], lapjvsp.triangle_pairs[lapjvsp.declared])
    np.testing.assert_array_equal(flow.pairs, lapjvsp.pairs)
