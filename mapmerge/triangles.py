"""Delaunay triangles of a landmark map, vertices in Groth order.

Groth (1986) orders a triangle's vertices by its side lengths so that the
same three landmarks get the same order in any rotated and translated copy:
side v1-v2 is the shortest, v2-v3 the intermediate and v3-v1 the longest, so
vertex 1 joins the shortest and longest sides. Equivalently, sorting the
vertices by the length of the side *opposite* them gives (v3, v1, v2).

Near-isosceles triangles swap order under small noise. That is a real
failure mode of the paper's method and is deliberately not hidden here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay

from ._validation import check_points


@dataclass(frozen=True)
class Triangles:
    """Triangles of one map.

    Attributes
    ----------
    vertices : (T, 3) int ndarray
        Landmark indices of each triangle, in Groth order.
    coords : (T, 3, 2) float ndarray
        The corresponding coordinates (the Groth 6-vector, reshaped).
    """

    vertices: np.ndarray
    coords: np.ndarray

    def __len__(self) -> int:
        return self.vertices.shape[0]


def groth_order(coords: np.ndarray) -> np.ndarray:
    """Permutation putting each triangle's vertices in Groth order.

    Parameters
    ----------
    coords : (T, 3, 2) ndarray
        Triangle vertex coordinates in any order.

    Returns
    -------
    (T, 3) int ndarray
        ``perm`` such that ``coords[t, perm[t]]`` is in Groth order.
    """
    # Side opposite vertex i joins the other two vertices.
    opposite = np.linalg.norm(
        np.roll(coords, -1, axis=1) - np.roll(coords, -2, axis=1), axis=2
    )
    # Ascending opposite length: shortest side is opposite v3, intermediate
    # opposite v1, longest opposite v2. Stable sort keeps exact ties
    # reproducible.
    by_opposite = np.argsort(opposite, axis=1, kind="stable")
    return by_opposite[:, [1, 2, 0]]


def triangulate(points) -> Triangles:
    """Delaunay-triangulate a map and put every triangle in Groth order.

    Parameters
    ----------
    points : (n, 2) array_like
        Landmark estimates, n >= 3, finite, distinct and not all collinear.

    Returns
    -------
    Triangles
        ``.vertices`` (T, 3) landmark indices and ``.coords`` (T, 3, 2).

    Raises
    ------
    ValueError
        If ``points`` is not a valid 2-D point set.
    """
    pts = check_points(points, "points")
    return _triangulate(pts)


def _triangulate(pts: np.ndarray) -> Triangles:
    simplices = Delaunay(pts).simplices
    perm = groth_order(pts[simplices])
    vertices = np.take_along_axis(simplices, perm, axis=1).astype(np.intp)
    return Triangles(vertices=vertices, coords=pts[vertices])


def delaunay_edges(points: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of the Delaunay graph, sorted."""
    points = np.asarray(points, dtype=float)
    simplices = Delaunay(points).simplices
    edges = np.sort(np.concatenate([simplices[:, [0, 1]], simplices[:, [1, 2]], simplices[:, [2, 0]]]), axis=1)
    n = len(points)
    keys = np.unique(edges[:, 0].astype(np.int64) * n + edges[:, 1])  # 1-D unique is much faster
    return np.stack([keys // n, keys % n], axis=1)
