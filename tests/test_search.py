"""The global transform search (method "search", and consensus's fallback)."""

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import metrics, search
from mapmerge.alignment import rotate


def transform_found(sc, res) -> bool:
    """Rotation within 1° and RMS registration error over the common landmarks within σ."""
    if not res.matched:
        return False
    _, ip, _ = np.intersect1d(sc.ids_p, sc.ids_q, return_indices=True)
    d = rotate(res.theta, sc.p[ip]) + res.t - (rotate(sc.theta, sc.p[ip]) + sc.t)
    err = metrics.map_errors(sc, res)
    return err["rot_err_deg"] < 1.0 and np.sqrt(np.mean(np.sum(d**2, axis=1) / 2)) <= sc.sigma


@pytest.mark.parametrize("snr, least", [(12.5, 8), (15.0, 10), (30.0, 10)])
def test_search_finds_the_transform_where_triangles_fail(snr, least):
    # Seeds 30-39 are not among the tuning or reported seeds. At 12.5 dB the
    # exhaustive detector itself finds 96 % (rotation within 1° is tight there).
    found = [transform_found(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method="search"))
             for sc in (mm.simulate.make_pair(100, 0.75, snr, rng=30 + k) for k in range(10))]
    assert sum(found) >= least


def test_consensus_falls_back_to_the_search_at_15_db():
    sc = mm.simulate.make_pair(100, 0.75, 15.0, rng=3)
    match = mm.merge_maps(sc.p, sc.q, sc.sigma, method="cyclic")
    assert not metrics.map_errors(sc, match)["success"]  # the triangles alone fail here
    res = mm.merge_maps(sc.p, sc.q, sc.sigma)
    assert transform_found(sc, res)
    assert metrics.map_errors(sc, res)["correct_pairs"] >= 0.8 * sc.n_common


@pytest.mark.parametrize("snr", [0.0, 10.0, 40.0])
def test_search_says_no_match_on_unrelated_maps(snr):
    for k in range(10):
        sc = mm.simulate.make_pair(100, 0.75, snr, rng=40 + k, unrelated=True)
        pairs, _, nfa = search.search_pairs(sc.p, sc.q, sc.sigma)
        assert len(pairs) == 0 and nfa > search.SEARCH_NFA


def test_search_with_isotropic_covariances_equals_sigma():
    sc = mm.simulate.make_pair(60, 0.75, 20.0, rng=5)
    cov = np.broadcast_to(sc.sigma**2 * np.eye(2), (60, 2, 2))
    a = search.search_pairs(sc.p, sc.q, sc.sigma, cov, cov)
    b = search.search_pairs(sc.p, sc.q, sc.sigma)
    assert np.array_equal(a[0], b[0]) and np.isclose(a[2], b[2])
    assert np.mean(sc.ids_p[a[0][:, 0]] == sc.ids_q[a[0][:, 1]]) > 0.8


def test_search_on_large_maps_votes_with_thinned_maps_and_finds_the_transform():
    # 2,000 landmarks per map vote with about 300 each; 15 dB, where triangles fail.
    sc = mm.simulate.make_pair(2000, 0.75, 15.0, rng=3)
    thinned = search._thinned(sc.p, search.MAX_SEARCH_LANDMARKS)
    assert 200 <= len(thinned) <= 450
    # The choice does not depend on the frame: rotated and shifted, the same landmarks are chosen.
    moved = search._thinned(rotate(1.0, sc.p) + [5.0, -3.0], search.MAX_SEARCH_LANDMARKS)
    assert np.allclose(rotate(1.0, thinned) + [5.0, -3.0], moved)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="search")
    assert transform_found(sc, res)
    unrelated = mm.simulate.make_pair(2000, 0.75, 15.0, rng=3, unrelated=True)
    assert not mm.merge_maps(unrelated.p, unrelated.q, unrelated.sigma, method="search").matched


@pytest.mark.parametrize("n", [1000, 7000])
def test_thinned_maps_are_the_local_maxima_over_all_k_nearest(n):
    """``_thinned`` checks all k nearest only for the landmarks that beat their nearest few: the same landmarks as
    checking every landmark against all k (k = 3 at 1,000 landmarks, 23 at 7,000, beyond the first check's 16)."""
    from scipy.spatial import cKDTree
    X = mm.simulate.make_pair(n, 0.75, 20.0, rng=5).p
    tree = cKDTree(X)
    rank = tree.query(X, k=search.THIN_RANK + 1)[0][:, search.THIN_RANK]
    neighbours = tree.query(X, k=round(n / search.MAX_SEARCH_LANDMARKS) + 1)[1][:, 1:]
    expected = X[np.all(rank[:, None] >= rank[neighbours], axis=1)]
    np.testing.assert_array_equal(search._thinned(X, search.MAX_SEARCH_LANDMARKS), expected)


def test_search_memo_answers_repeated_searches_once_and_bit_for_bit(monkeypatch):
    sc = mm.simulate.make_pairs(40, 0.75, 20, [7, 8, 9])
    alone = [search.search_pairs(sc.p[b], sc.q[b], sc.sigma[b]) for b in range(3)]
    assert all(len(pairs) >= 3 for pairs, _, _ in alone)
    searched = []
    real = search.search_batch
    monkeypatch.setattr(search, "search_batch", lambda P, *a: searched.append(len(P)) or real(P, *a))
    memo = search.SearchMemo()
    rows = np.array([1, 0, 1])  # a repeated pair is searched once
    a = memo(sc.p[rows], sc.q[rows], sc.sigma[rows])
    a[1][:] = -1  # the caller's copy, not the memo's
    trial, pairs, contested, nfa = memo(sc.p[rows], sc.q[rows], sc.sigma[rows])
    assert searched == [2]
    for k, b in enumerate(rows):
        assert np.array_equal(pairs[trial == k], alone[b][0]) and np.array_equal(contested[trial == k], alone[b][1])
        assert nfa[k] == alone[b][2]
    memo(sc.p, sc.q, sc.sigma)  # only the pair not seen before is searched
    memo(sc.p[:1], sc.q[:1], sc.sigma[:1], sc.cov_p[:1], sc.cov_q[:1])  # other inputs: searched again
    assert searched == [2, 1, 1]


@pytest.mark.parametrize("anisotropy", [0.0, 0.5])
def test_search_batch_equals_each_pair_searched_alone(anisotropy):
    sc = mm.simulate.make_pairs(30, 0.75, 15, list(range(20, 28)), anisotropy=anisotropy)
    cov = (sc.cov_p, sc.cov_q) if anisotropy else (None, None)
    trial, pairs, contested, nfa = search.search_batch(sc.p, sc.q, sc.sigma, *cov)
    assert 0 < len(np.unique(trial)) < len(sc)  # some pairs found, some not
    for b in range(len(sc)):
        alone = search.search_pairs(sc.p[b], sc.q[b], sc.sigma[b], *(None if c is None else c[b] for c in cov))
        assert np.array_equal(pairs[trial == b], alone[0]) and np.array_equal(contested[trial == b], alone[1])
        assert nfa[b] == alone[2]


def test_search_declines_where_the_noise_is_comparable_to_the_landmark_spacing():
    # At 0 dB the pair noise is 0.65-1.3 landmark spacings: there the search's null bound fails
    # (unrelated pairs passed it at NFA 2e-10), so the search must not run; at 10 dB it does.
    from scipy.spatial import ConvexHull

    from mapmerge.exhaustive import pair_noise

    for rng, snr, declines in ((60, 0.0, True), (61, 0.0, True), (60, 10.0, False)):
        sc = mm.simulate.make_pair(100, 0.75, snr, rng=rng, unrelated=snr == 0.0)
        spacing = np.sqrt(ConvexHull(sc.p).volume / len(sc.p))
        assert (pair_noise(sc.sigma) > search.MAX_NOISE_SPACING * spacing) == declines
        pairs, _, nfa = search.search_pairs(sc.p, sc.q, sc.sigma)
        assert (nfa == np.inf) == declines and (len(pairs) == 0 or not declines)


def test_hypotheses_of_many_pairs_refined_together_give_each_refined_alone():
    # Coarse hypotheses at 10 dB: some refine to the transform, some to chance alignments, some die.
    from scipy.spatial import ConvexHull

    sc = mm.simulate.make_pairs(60, 0.75, 10.0, list(range(6)))
    r = np.sqrt(2.0) * sc.sigma
    area = np.array([ConvexHull(p).volume for p in sc.p])
    pair, thetas, ts, cell, _ = search._hypotheses(list(sc.p), list(sc.q), r, area)
    assert np.array_equal(np.unique(pair), np.arange(6))
    # One more per map pair that pairs nothing.
    first = np.searchsorted(pair, np.arange(6))
    order = np.argsort(np.r_[pair, np.arange(6)], kind="stable")
    pair, thetas = np.r_[pair, np.arange(6)][order], np.r_[thetas, thetas[first] + 2.0][order]
    ts = np.r_[ts, ts[first] + 1e6][order]
    together = search._refine(list(sc.p), list(sc.q), pair, thetas, ts, r, cell)
    kept = 0
    for k, b in enumerate(pair):
        alone = search._refine([sc.p[b]], [sc.q[b]], np.array([0]), thetas[k:k + 1], ts[k:k + 1], r[b:b + 1],
                               cell[b:b + 1])
        if alone.pair.size:
            assert together.pair[kept] == b
            assert together.theta[kept] == alone.theta[0] and np.array_equal(together.t[kept], alone.t[0])
            assert together.cost[kept] == alone.cost[0]
            mine = together.h == kept
            assert np.array_equal(together.i[mine], alone.i) and np.array_equal(together.j[mine], alone.j)
            kept += 1
    assert kept == together.pair.size and 20 <= kept <= len(pair) - 6


@pytest.mark.parametrize("scale", [1e3, 1e9, 1e48, 1e-9])
def test_maps_in_different_units_cost_what_same_unit_maps_cost(scale):
    """q in other units (x 1e3 ... 1e48) once asked for a vote grid of 10¹¹ cells or overflowed: the grid
    is now coarsened to ``MAX_VOTE_CELLS`` per axis, and only cells holding votes are scored."""
    import tracemalloc

    sc = mm.simulate.make_pair(45, 0.75, 30, rng=0)
    tracemalloc.start()
    try:
        pairs, _, nfa = search.search_pairs(sc.p, sc.q * scale, 0.3)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(pairs) == 0 and not nfa <= search.SEARCH_NFA
    assert peak < 400 * 2**20, f"{peak / 2**20:.0f} MiB"
