import numpy as np
import pytest

import mapmerge as mm


def _sides(coords):
    return (
        np.linalg.norm(coords[:, 0] - coords[:, 1], axis=1),
        np.linalg.norm(coords[:, 1] - coords[:, 2], axis=1),
        np.linalg.norm(coords[:, 2] - coords[:, 0], axis=1),
    )


def test_groth_order_sides(rng):
    tri = mm.triangulate(rng.uniform(0, 10, size=(60, 2)))
    s12, s23, s31 = _sides(tri.coords)
    assert np.all(s12 <= s23) and np.all(s23 <= s31)
    assert tri.vertices.shape == (len(tri), 3) and tri.coords.shape == (len(tri), 3, 2)
    assert tri.vertices.dtype.kind == "i"


def test_same_triangles_as_delaunay(rng):
    from scipy.spatial import Delaunay

    pts = rng.uniform(0, 10, size=(40, 2))
    tri = mm.triangulate(pts)
    ref = {tuple(sorted(s)) for s in Delaunay(pts).simplices.tolist()}
    assert {tuple(sorted(v)) for v in tri.vertices.tolist()} == ref


def test_order_invariant_to_rigid_motion(rng):
    pts = rng.uniform(0, 10, size=(50, 2))
    moved = pts @ mm.rotation(1.234).T + [7.0, -3.0]
    a = {tuple(v) for v in mm.triangulate(pts).vertices.tolist()}
    b = {tuple(v) for v in mm.triangulate(moved).vertices.tolist()}
    assert a == b


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((2, 2)), "at least 3"),
        (np.zeros((5, 3)), r"shape \(n, 2\)"),
        (np.array([[0, 0], [1, np.nan], [0, 1.0]]), "NaN or inf"),
        (np.array([[0, 0], [1, np.inf], [0, 1.0]]), "NaN or inf"),
        (np.array([[0, 0], [1, 1], [2, 2.0], [3, 3]]), "collinear"),
        (np.array([[0, 0], [1, 0], [0, 1.0], [1, 0]]), "duplicate"),
        ("abc", "points must"),
    ],
)
def test_triangulate_rejects_bad_input(points, match):
    with pytest.raises(ValueError, match=match):
        mm.triangulate(points)


def test_large_maps_triangulated_in_threads_give_the_same_triangles(monkeypatch, rng):
    from mapmerge import triangles

    P, Q = rng.uniform(0, 100, size=(1, 3000, 2)), rng.uniform(0, 100, size=(1, 2000, 2))
    serial = triangles.triangulate_batches(P, Q)
    monkeypatch.setattr(triangles, "PARALLEL_MIN_LANDMARKS", 1000)
    threaded = triangles.triangulate_batches(P, Q)
    for a, b in zip(serial, threaded):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.offsets, b.offsets)


def test_map_hulls_are_computed_once_and_shared_by_their_views(monkeypatch):
    from mapmerge import triangles

    maps = mm.simulate.make_pairs(12, 0.75, 30.0, [1, 2, 3, 4]).p
    made = []
    real = triangles.ConvexHull
    monkeypatch.setattr(triangles, "ConvexHull", lambda X: made.append(1) or real(X))
    hulls = triangles.MapHulls(maps)
    view = hulls.take(np.array([3, 1]))
    assert len(view) == 2 and view[0].volume == real(maps[3]).volume
    assert hulls[3] is view[0] and view.take(np.array([1]))[0] is hulls[1] and len(made) == 2
    np.testing.assert_array_equal(hulls[2].equations, real(maps[2]).equations)
    assert len(made) == 3
