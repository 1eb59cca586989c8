"""The memory- and cache-saving paths of large maps give what the direct ones give, on small maps."""

import numpy as np
from scipy.spatial import Delaunay

import mapmerge as mm
from mapmerge import alignment, matching, triangles

LOG_TAU = mm.resolve_log_tau("chi2:0.01")


def _triangle_set(simplices):
    return {tuple(sorted(s)) for s in simplices.tolist()}


def test_paired_transforms_in_blocks_gives_the_same_bits(monkeypatch, rng):
    cp = rng.normal(size=(2000, 3, 2))
    cq = cp @ alignment.rotation(0.7).T + rng.normal(0, 0.01, size=(2000, 3, 2)) + [3.0, -1.0]
    whole = alignment.paired_transforms(cp, cq)
    monkeypatch.setattr(alignment, "PAIRED_CHUNK", 300)  # 7 blocks, the last one short
    blocks = alignment.paired_transforms(cp, cq)
    for a, b in zip(whole, blocks):
        assert np.array_equal(a, b)


def test_sorted_delaunay_has_qhulls_triangles(monkeypatch):
    sc = mm.simulate.make_pair(2000, 0.75, 30, rng=5)
    monkeypatch.setattr(triangles, "SORTED_DELAUNAY_MIN_LANDMARKS", 0)
    sorted_tri = triangles.delaunay_simplices(sc.p)
    assert _triangle_set(sorted_tri) == _triangle_set(Delaunay(sc.p).simplices)
    # Groth order is a property of each triangle's geometry, whatever order Qhull returned it in.
    groth = triangles.triangulate(sc.p).vertices
    key = {tuple(sorted(v)): tuple(v) for v in groth.tolist()}
    monkeypatch.setattr(triangles, "SORTED_DELAUNAY_MIN_LANDMARKS", 10**9)
    assert key == {tuple(sorted(v)): tuple(v) for v in triangles.triangulate(sc.p).vertices.tolist()}


def test_z_order_is_a_permutation_along_the_curve(rng):
    x = rng.random((500, 3))
    order = triangles.z_order(x)
    assert np.array_equal(np.sort(order), np.arange(500))
    # Neighbours along the curve are close: far closer on average than in the given (random) order.
    step = np.linalg.norm(np.diff(x[order], axis=0), axis=1).mean()
    assert step < 0.5 * np.linalg.norm(np.diff(x, axis=0), axis=1).mean()


def test_candidate_queries_in_z_order_give_the_same_pairs(monkeypatch):
    sc = mm.simulate.make_pair(2000, 0.75, 30, rng=6)
    tp, tq = mm.triangulate(sc.p).coords, mm.triangulate(sc.q).coords
    direct = matching.candidate_pairs(tp, tq, sc.sigma, LOG_TAU, 8)
    monkeypatch.setattr(matching, "PARALLEL_MIN_LANDMARKS", 10)  # the large-map path: sorted, 2 workers
    assert np.array_equal(matching.candidate_pairs(tp, tq, sc.sigma, LOG_TAU, 8), direct)


def test_consensus_on_a_2000_landmark_pair_is_unchanged_by_the_large_map_paths(monkeypatch):
    sc = mm.simulate.make_pair(2000, 0.75, 30, rng=4)
    before = mm.merge_maps(sc.p, sc.q, sc.sigma)
    monkeypatch.setattr(alignment, "PAIRED_CHUNK", 1000)
    monkeypatch.setattr(matching, "PARALLEL_MIN_LANDMARKS", 10)
    after = mm.merge_maps(sc.p, sc.q, sc.sigma)
    assert np.array_equal(before.pairs, after.pairs) and before.theta == after.theta
    assert np.array_equal(before.merged, after.merged) and np.array_equal(before.triangle_pairs, after.triangle_pairs)
