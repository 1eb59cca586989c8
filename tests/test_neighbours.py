"""The grid neighbour search against scipy's k-d tree, and the compiled kernels against their Python source."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

import mapmerge as mm
from mapmerge import exhaustive, neighbours


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_grid_counts_and_nearest_neighbours_are_the_k_d_trees(rng, scale):
    for _ in range(200):
        m, n = rng.integers(1, 60, 2)
        P = rng.uniform(0, 1, (n, 2)) * scale * 10.0 ** rng.uniform(-2, 2)
        x = np.concatenate([rng.uniform(-0.2, 1.2, (m, 2)) * P.max(), P[rng.integers(0, n, 3)]])
        radius = float(rng.uniform(0.01, 1.0) * P.max())
        grid = neighbours.cell_grid(P, radius)
        tree = cKDTree(P)
        # Points on the radius itself may fall either side of it by rounding: compare off the boundary.
        d = np.sqrt(((x[:, None] - P[None]) ** 2).sum(-1))
        clear = np.all(np.abs(d - radius) > 1e-9 * radius, axis=1)
        count = neighbours.count_within(x, grid, radius)
        np.testing.assert_array_equal(count[clear], tree.query_ball_point(x, radius, return_length=True)[clear])
        near, dist = neighbours.nearest_within(x, *grid.arrays(), radius)
        t_dist, t_near = tree.query(x, distance_upper_bound=radius)
        found = np.isfinite(t_dist) & (t_dist < radius)
        np.testing.assert_array_equal(near >= 0, found)
        np.testing.assert_allclose(dist[found], t_dist[found], rtol=1e-12)
        np.testing.assert_array_equal(near[found], np.argmin(d, axis=1)[found])


def test_grids_of_a_batch_of_maps_are_each_map_s_own(rng):
    X = rng.uniform(-1, 1, (6, 40, 2)) * 10.0 ** rng.uniform(-3, 3, (6, 1, 1))
    radius = rng.uniform(0.01, 0.5, 6) * np.abs(X).max(axis=(1, 2))
    for together, (P, r) in zip(neighbours.cell_grids(X, radius), zip(X, radius)):
        alone = neighbours.cell_grids(P[None], [r])[0]
        assert (together.h, together.nx, together.ny) == (alone.h, alone.nx, alone.ny) and together.nx * together.ny > 4
        for a, b in zip(together.arrays()[:4], alone.arrays()[:4]):
            np.testing.assert_array_equal(a, b)
        assert np.all(np.diff(together.keys) >= 0) and np.array_equal(together.points, P[together.index])


def test_grid_of_points_spread_over_any_extent_keeps_its_keys_in_range():
    P = np.array([[0.0, 0.0], [1e300, 1.0], [-1e300, 5.0]])
    grid = neighbours.cell_grid(P, 1e-12)
    assert grid.nx <= neighbours.MAX_CELLS_PER_AXIS and grid.ny <= neighbours.MAX_CELLS_PER_AXIS
    assert neighbours.count_within(P, grid, 1e-12).tolist() == [1, 1, 1]


def test_compiled_mixture_kernels_equal_their_python_source():
    """numba is optional: without it the same functions run as Python. Both give the same numbers."""
    em = exhaustive._em_rounds
    if not hasattr(em, "py_func"):
        pytest.skip("numba is not installed: the kernels already run as Python")
    sc = mm.simulate.make_pair(40, 0.75, 20, rng=3)
    s = np.sqrt(2) * sc.sigma
    model = exhaustive.Mixture.of_map(sc.p, s, exhaustive.bump_height(sc.density, 1.0, s, 0.5), 0.5)
    args = (sc.q, sc.theta + 0.01, sc.t[0] + 0.1, sc.t[1], model.hull.equations, s, model.c, exhaustive.EXACT_RADIUS * s,
            exhaustive.EM_ROUNDS, *model.grid.arrays())
    np.testing.assert_allclose(em(*args), em.py_func(*args), rtol=1e-12)
    x = sc.q[:20]
    # bump_sums is _bumps_and_cover at one radius, so the loop to check is _bumps_and_cover's.
    grid = model.grid.arrays()
    python = exhaustive._bumps_and_cover.py_func(x, s, 5 * s, 5 * s, *grid)[0]
    np.testing.assert_allclose(exhaustive.bump_sums(x, s, 5 * s, *grid), python, rtol=1e-12)
    np.testing.assert_allclose(exhaustive._bumps_and_cover(x, s, 5 * s, 5 * s, *grid)[0], python, rtol=1e-12)


def test_quadrature_bumps_and_cover_are_the_two_searches_in_one():
    sc = mm.simulate.make_pair(40, 0.75, 20, rng=4)
    s = np.sqrt(2) * sc.sigma
    model = exhaustive.Mixture.of_map(sc.p, s, exhaustive.bump_height(sc.density, 1.0, s, 0.5), 0.5)
    x = np.concatenate([sc.q, sc.p + 2 * s])
    radius = exhaustive.EXACT_RADIUS * s
    bumps, cover = exhaustive._bumps_and_cover(x, s, 0.5 * radius, radius, *model.grid.arrays())
    np.testing.assert_array_equal(bumps, exhaustive.bump_sums(x, s, 0.5 * radius, *model.grid.arrays()))
    np.testing.assert_array_equal(cover, neighbours.count_within(x, model.grid, radius))
    assert cover.sum() > np.count_nonzero(bumps)  # the two radii differ, so the test can tell them apart


def test_cached_kernels_are_dropped_when_any_source_changes(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    kernels = [tmp_path / "__pycache__" / "a.f-1.py311.nbi", tmp_path / "sub" / "__pycache__" / "b.g-1.py311.1.nbc"]

    def compile_kernels():
        for path in kernels:
            path.parent.mkdir(exist_ok=True)
            path.write_bytes(b"machine code")

    compile_kernels()
    assert neighbours.clear_stale_kernels(tmp_path)  # no digest yet: nothing is trusted
    assert not any(path.exists() for path in kernels)
    compile_kernels()
    assert not neighbours.clear_stale_kernels(tmp_path)  # same sources: kept
    assert all(path.exists() for path in kernels)
    (tmp_path / "sub" / "b.py").write_text("y = 3\n")  # a callee's module changed
    assert neighbours.clear_stale_kernels(tmp_path)
    assert not any(path.exists() for path in kernels)
