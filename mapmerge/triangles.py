"""Delaunay triangles of landmark maps, vertices in Groth order.

Groth (1986) orders a triangle's vertices by its side lengths so that the
same three landmarks get the same order in any rotated and translated copy:
side v1-v2 is the shortest, v2-v3 the intermediate and v3-v1 the longest, so
vertex 1 joins the shortest and longest sides. Equivalently, sorting the
vertices by the length of the side *opposite* them gives (v3, v1, v2).

Near-isosceles triangles swap order under small noise. That is a real
failure mode of the paper's method and is deliberately not hidden here.

Maps come in batches: ``triangulate_batch`` takes B maps of equal size and
returns their triangles as one ragged array (triangles of map b are rows
``offsets[b]:offsets[b + 1]``); ``triangulate`` is the batch of one. Only
the Delaunay call itself runs per map.
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, Delaunay

from ._validation import check_points

#: Maps of at least this many landmarks are triangulated in parallel threads
#: (Qhull releases the GIL), and their triangles' neighbour queries too.
#: Smaller maps stay in one thread: the harness already runs one process
#: per core, and a thread costs more than a small Delaunay call.
PARALLEL_MIN_LANDMARKS = 20_000
#: Maps of at least this many landmarks are handed to Qhull sorted along a
#: Z-order curve (``z_order``), so that it inserts neighbours one after
#: another and works in cache: 22 s -> 16 s of CPU at 10^6 landmarks (two
#: engineers' jobs sharing the machine). The triangles are the same, their
#: order is not; below this, up to the 10^5-landmark maps of every reported
#: result, Qhull gets the map as given and its order is kept.
SORTED_DELAUNAY_MIN_LANDMARKS = 200_000


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


class MapHulls:
    """The convex hulls (Qhull) of a batch of maps, each computed on first use and kept: the stages that
    need a map's hull (its density, inside tests) share one, also across merges of the same maps at other
    thresholds (``take`` gives a view that shares them)."""

    def __init__(self, maps: np.ndarray, rows=None, known: dict | None = None) -> None:
        # ``rows`` and ``known``: a view's rows of ``maps`` and the hulls it shares (``take``).
        self._maps = maps
        self._rows = np.arange(len(maps)) if rows is None else rows
        self._known = {} if known is None else known

    def __len__(self) -> int:
        return len(self._rows)

    def __getitem__(self, b) -> ConvexHull:
        row = int(self._rows[b])
        if row not in self._known:
            self._known[row] = ConvexHull(self._maps[row])
        return self._known[row]

    def take(self, maps) -> "MapHulls":
        """The hulls of maps ``maps`` (indices), renumbered 0..len(maps)-1, shared with this batch."""
        return MapHulls(self._maps, self._rows[maps], self._known)


@dataclass(frozen=True)
class TriangleBatch:
    """Triangles of B maps as one ragged array.

    Attributes
    ----------
    maps : (B, n, 2) ndarray
        The triangulated maps.
    vertices : (S, 3) int ndarray
        Landmark indices (into each triangle's own map), Groth order.
    trial : (S,) int ndarray
        Map of each triangle; triangles of one map are contiguous.
    offsets : (B + 1,) int ndarray
        Map b's triangles are rows ``offsets[b]:offsets[b + 1]``.
    hulls : MapHulls
        The maps' convex hulls, computed on first use.
    """

    maps: np.ndarray
    vertices: np.ndarray
    trial: np.ndarray
    offsets: np.ndarray
    hulls: MapHulls = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.hulls is None:
            object.__setattr__(self, "hulls", MapHulls(self.maps))

    def __len__(self) -> int:
        return self.offsets.size - 1

    @functools.cached_property
    def count(self) -> np.ndarray:
        """Triangles per map, (B,)."""
        return self.offsets[1:] - self.offsets[:-1]

    @property
    def slot(self) -> np.ndarray:
        """Index of each triangle within its own map, (S,)."""
        return np.arange(self.trial.size) - self.offsets[self.trial]

    def flat_vertices(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """Row indices into ``maps.reshape(-1, 2)`` of each vertex, (S, 3)."""
        v = self.vertices if vertices is None else vertices
        return self.trial[:, None] * self.maps.shape[1] + v

    def coords(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """Vertex coordinates (S, 3, 2), in the order of ``vertices`` (default Groth)."""
        # np.take, not fancy indexing: rows of two floats gather several times faster (a copy, the same bits).
        return np.take(self.maps.reshape(-1, 2), self.flat_vertices(vertices), axis=0)

    def ccw_vertices(self) -> np.ndarray:
        """Vertices put counter-clockwise (``ccw_order``), (S, 3)."""
        return np.take_along_axis(self.vertices, ccw_order(self.coords()), axis=1)

    def padded(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """Vertices as (B, T_max, 3); rows past a map's own triangles point at landmark 0."""
        v = self.vertices if vertices is None else vertices
        out = np.zeros((len(self), int(self.count.max(initial=0)), 3), dtype=np.intp)
        out[self.trial, self.slot] = v
        return out

    def take(self, maps: np.ndarray) -> "TriangleBatch":
        """The triangles of maps ``maps`` (indices, increasing), renumbered 0..len(maps)-1."""
        count = self.count[maps]
        rows = np.repeat(self.offsets[maps] - np.r_[0, np.cumsum(count)[:-1]], count) + np.arange(count.sum())
        return TriangleBatch(maps=self.maps[maps], vertices=self.vertices[rows],
                             trial=np.repeat(np.arange(len(maps)), count), offsets=np.r_[0, np.cumsum(count)],
                             hulls=self.hulls.take(maps))

    def __getitem__(self, b: int) -> Triangles:
        vertices = self.vertices[self.offsets[b]:self.offsets[b + 1]]
        return Triangles(vertices=vertices, coords=np.take(self.maps[b], vertices, axis=0))


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
    v0, v1, v2 = coords[:, 0], coords[:, 1], coords[:, 2]
    o0, o1, o2 = _length(v1 - v2), _length(v2 - v0), _length(v0 - v1)
    # Ascending opposite length: shortest side is opposite v3, intermediate
    # opposite v1, longest opposite v2. Each vertex's rank in a stable sort
    # (exact ties keep index order), by comparisons: far cheaper than an
    # argsort over a length-3 axis. Rank r goes to Groth slot (r + 2) % 3.
    rows = np.arange(len(coords))
    perm = np.empty((len(coords), 3), dtype=np.intp)
    perm[rows, ((o1 < o0).astype(np.intp) + (o2 < o0) + 2) % 3] = 0
    perm[rows, ((o0 <= o1).astype(np.intp) + (o2 < o1) + 2) % 3] = 1
    perm[rows, ((o0 <= o2).astype(np.intp) + (o1 <= o2) + 2) % 3] = 2
    return perm


def _length(d: np.ndarray) -> np.ndarray:
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


def centroids(coords: np.ndarray) -> np.ndarray:
    """Centroid of each triangle (..., 3, 2): the vertices summed in order, then divided by 3, which are the
    bits of ``coords.mean(axis=-2)`` at a fraction of its cost (a reduction over a middle axis is slow)."""
    return ((coords[..., 0, :] + coords[..., 1, :]) + coords[..., 2, :]) / 3


def ccw_order(coords: np.ndarray) -> np.ndarray:
    """Permutation (T, 3) putting each triangle's vertices counter-clockwise."""
    d1, d2 = coords[:, 1] - coords[:, 0], coords[:, 2] - coords[:, 0]
    clockwise = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] < 0
    return np.where(clockwise[:, None], [0, 2, 1], [0, 1, 2])


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
    return triangulate_batch(pts[None])[0]


def triangulate_batch(maps: np.ndarray) -> TriangleBatch:
    """Delaunay triangles, in Groth order, of B maps of n landmarks each.

    Parameters
    ----------
    maps : (B, n, 2) ndarray
        Valid maps (as ``triangulate`` checks them; not re-checked here).

    Returns
    -------
    TriangleBatch
    """
    simplices = [delaunay_simplices(pts) for pts in maps]
    if len(simplices) == 1:  # one map: no bookkeeping across maps
        flat = simplices[0].astype(np.intp)
        trial, offsets = np.zeros(len(flat), np.intp), np.array([0, len(flat)])
        perm = groth_order(np.take(maps[0], flat, axis=0))
    else:
        count = np.array([len(s) for s in simplices], dtype=np.intp)
        offsets = np.concatenate(([0], np.cumsum(count)))
        trial = np.repeat(np.arange(len(maps)), count)
        flat = np.concatenate(simplices).astype(np.intp, copy=False)
        perm = groth_order(maps.reshape(-1, 2)[trial[:, None] * maps.shape[1] + flat])
    return TriangleBatch(maps=maps, vertices=flat[np.arange(len(flat))[:, None], perm],
                         trial=trial, offsets=offsets)


def triangulate_batches(*batches: np.ndarray) -> tuple[TriangleBatch, ...]:
    """``triangulate_batch`` of each batch (e.g. the p maps and the q maps).

    Batches of large maps (``PARALLEL_MIN_LANDMARKS``) run in parallel
    threads; the triangles are the same either way.
    """
    if min(b.shape[1] for b in batches) < PARALLEL_MIN_LANDMARKS:
        return tuple(triangulate_batch(b) for b in batches)
    with ThreadPoolExecutor(len(batches)) as pool:
        return tuple(pool.map(triangulate_batch, batches))


def delaunay_simplices(points: np.ndarray) -> np.ndarray:
    """Landmark indices (T, 3) of the Delaunay triangles of one map (sorted first when large,
    ``SORTED_DELAUNAY_MIN_LANDMARKS``)."""
    if len(points) < SORTED_DELAUNAY_MIN_LANDMARKS:
        return Delaunay(points).simplices
    order = z_order(points)
    return order[Delaunay(points[order]).simplices]


def z_order(points: np.ndarray, bits: int = 16) -> np.ndarray:
    """The permutation (n,) sorting points (n, d), d <= 3, along a Z-order (Morton) curve over their
    bounding box, cells ``2**-bits`` of its sides wide (ties in index order)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    cell = ((points - lo) / np.where(hi > lo, hi - lo, 1.0) * (2**bits - 1)).astype(np.int64)
    d = points.shape[1]
    key = np.zeros(len(points), np.int64)
    for b in range(bits):  # interleave the bits of the cell indices
        for axis in range(d):
            key |= ((cell[:, axis] >> b) & 1) << (d * b + axis)
    return np.argsort(key, kind="stable")


def delaunay_edges(points: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of the Delaunay graph, sorted."""
    points = np.asarray(points, dtype=float)
    simplices = Delaunay(points).simplices
    edges = np.sort(np.concatenate([simplices[:, [0, 1]], simplices[:, [1, 2]], simplices[:, [2, 0]]]), axis=1)
    n = len(points)
    keys = np.unique(edges[:, 0].astype(np.int64) * n + edges[:, 1])  # 1-D unique is much faster
    return np.stack([keys // n, keys % n], axis=1)
