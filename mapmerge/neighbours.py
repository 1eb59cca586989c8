"""Fixed-radius neighbours of a map's landmarks: a uniform grid, searched by compiled kernels.

The mixture model's EM, its exact likelihood ratio and its null-tail
quadrature (``mapmerge.exhaustive``) and the global search's refinement
(``mapmerge.search``) all ask, many times over, which landmarks of one map
lie within a radius of some points. ``CellGrid`` sorts the landmarks by
the cell of a grid at least that radius wide, so that every neighbour of a
point lies in the 3 x 3 cells around it; the cells are found by binary
search in the sorted keys (three cells of one column are one range of
them), so memory is O(n) whatever the maps' extent, and the same structure
serves 10 landmarks and 10⁶.

The kernels are compiled by numba (the ``fast`` extra, ``cache=True``: the
machine code is kept beside the sources after the first call). Without
numba the very same functions run as Python: the same results, slowly.
numba checks a cached kernel against its own file only, so one that calls
a kernel of another module would go on running the old callee after that
module changed; ``clear_stale_kernels`` therefore drops the package's
cached kernels whenever any of its sources changed.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no lock, the check still runs
    fcntl = None
try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised where numba is absent
    def njit(*args, **kwargs):
        """numba's decorator when numba is absent: the function unchanged."""
        if len(args) == 1 and callable(args[0]) and not kwargs:
            return args[0]
        return lambda function: function


def clear_stale_kernels(package: Path = Path(__file__).parent) -> bool:
    """Delete the numba caches (``__pycache__/*.nbi``, ``*.nbc``) under ``package`` unless its ``.py`` sources are
    the ones they were compiled from (a digest kept in ``__pycache__/kernels.sha256``); True when deleted.

    Run at import, before any kernel is compiled (numba compiles at the first call), under a lock, so that
    processes starting together (workers, test processes) check and delete once. A read-only install keeps
    its caches as they are.
    """
    digest = hashlib.sha256()
    for source in sorted(package.rglob("*.py")):
        digest.update(source.relative_to(package).as_posix().encode() + b"\0" + source.read_bytes())
    cache = package / "__pycache__"
    try:
        cache.mkdir(exist_ok=True)
        with open(cache / "kernels.lock", "w") as lock:
            if fcntl is not None:
                fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
            stamp = cache / "kernels.sha256"
            if stamp.is_file() and stamp.read_text() == digest.hexdigest():
                return False
            for cached in (*package.rglob("*.nbi"), *package.rglob("*.nbc")):
                cached.unlink(missing_ok=True)
            stamp.write_text(digest.hexdigest())
    except OSError:
        return False
    return True


clear_stale_kernels()

#: Largest number of grid cells per axis. Cells are widened beyond it, so points spread over any extent
#: (maps in other units) still give keys that fit an int64; wider cells only cost more comparisons.
MAX_CELLS_PER_AXIS = 2**24


@dataclass(frozen=True)
class CellGrid:
    """Points sorted by the cell of a uniform grid (``cell_grid``).

    Attributes
    ----------
    points : (n, 2) ndarray
        The points, sorted by cell key.
    index : (n,) int64 ndarray
        Each sorted point's index in the input.
    keys : (n,) int64 ndarray
        Their cell keys ``ix * ny + iy``, ascending.
    origin : (2,) ndarray
        The corner of cell (0, 0).
    h : float
        The cell width (at least the radius the grid was built for).
    nx, ny : int
        Cells per axis.
    """

    points: np.ndarray
    index: np.ndarray
    keys: np.ndarray
    origin: np.ndarray
    h: float
    nx: int
    ny: int

    def arrays(self):
        """The grid as the positional arguments of the kernels."""
        return self.points, self.index, self.keys, self.origin[0], self.origin[1], self.h, self.nx, self.ny


def cell_grid(P: np.ndarray, radius: float) -> CellGrid:
    """Sort P (n, 2) on a grid whose cells are at least ``radius`` wide (valid, finite input)."""
    return cell_grids(P[None], [radius])[0]


def cell_grids(X: np.ndarray, radius) -> list[CellGrid]:
    """``cell_grid`` of B maps of one size at once: X (B, n, 2), one radius per map."""
    origin = X.min(axis=1)
    extent = np.max(X.max(axis=1) - origin, axis=1)
    h = np.maximum(np.maximum(np.asarray(radius, dtype=float), extent / (MAX_CELLS_PER_AXIS - 1)),
                   np.finfo(float).tiny)
    cells = np.floor((X - origin[:, None]) / h[:, None, None]).astype(np.int64)
    n_cells = cells.max(axis=1) + 1
    keys = cells[..., 0] * n_cells[:, 1:] + cells[..., 1]
    order = np.argsort(keys, axis=1, kind="stable")
    points = np.take_along_axis(X, order[..., None], axis=1)
    keys = np.take_along_axis(keys, order, axis=1)
    return [CellGrid(points[b], order[b], keys[b], origin[b], float(h[b]), int(n_cells[b, 0]), int(n_cells[b, 1]))
            for b in range(len(X))]


def ragged_starts(parts) -> np.ndarray:
    """Offsets of arrays laid end to end: part k is rows ``start[k]:start[k + 1]``."""
    return np.concatenate([[0], np.cumsum([len(x) for x in parts])]).astype(np.int64)


def stacked_grids(grids) -> tuple:
    """Grids laid end to end, for the kernels that visit many: (points, index, keys, start, ox, oy, h, nx,
    ny), grid g's points being rows ``start[g]:start[g + 1]`` and its other values entry g."""
    return (np.concatenate([g.points for g in grids]), np.concatenate([g.index for g in grids]),
            np.concatenate([g.keys for g in grids]), ragged_starts([g.points for g in grids]),
            np.array([g.origin[0] for g in grids]),
            np.array([g.origin[1] for g in grids]), np.array([g.h for g in grids]),
            np.array([g.nx for g in grids], dtype=np.int64), np.array([g.ny for g in grids], dtype=np.int64))


@njit(cache=True)
def column_span(x, y, keys, ox, oy, h, nx, ny, ix_off):
    """The range of sorted points in the three cells (ix + ix_off, iy - 1 .. iy + 1) around the cell
    (ix, iy) holding (x, y), the part of them on the grid; an empty range when none is (or x, y is not
    finite).

    Keys run ``ix * ny + iy``, so the three cells are consecutive in the sorted points, in the order of
    iy: one range, two binary searches instead of six.
    """
    fx = np.floor((x - ox) / h) + ix_off
    fy = np.floor((y - oy) / h)
    lo_y, hi_y = max(fy - 1, 0.0), min(fy + 1, ny - 1.0)
    if not (fx >= 0 and fx < nx and lo_y <= hi_y):
        return 0, 0
    row = np.int64(fx) * ny
    return np.searchsorted(keys, row + np.int64(lo_y)), np.searchsorted(keys, row + np.int64(hi_y), side="right")


@njit(cache=True)
def pairs_within(x, points, index, keys, ox, oy, h, nx, ny, radius):
    """Every (row of x, point) pair within ``radius`` (at most the grid's h), grouped by row of x.

    Returns
    -------
    start : (m + 1,) int64 ndarray
        Row j's pairs are ``start[j]:start[j + 1]``.
    k : int64 ndarray
        Each pair's point, as its position in the grid's sorted ``points``.
    d2 : ndarray
        Each pair's squared distance.
    """
    r2 = radius * radius
    start = np.zeros(x.shape[0] + 1, dtype=np.int64)
    # Counted first, then filled: no growing buffers; the first pass keeps the columns' ranges.
    span = np.empty((x.shape[0], 6), dtype=np.int64)
    for j in range(x.shape[0]):
        n = start[j]
        for a in range(3):
            lo, hi = column_span(x[j, 0], x[j, 1], keys, ox, oy, h, nx, ny, a - 1)
            span[j, 2 * a], span[j, 2 * a + 1] = lo, hi
            for c in range(lo, hi):
                dx, dy = x[j, 0] - points[c, 0], x[j, 1] - points[c, 1]
                if dx * dx + dy * dy <= r2:
                    n += 1
        start[j + 1] = n
    k, d2 = np.empty(start[-1], dtype=np.int64), np.empty(start[-1])
    for j in range(x.shape[0]):
        n = start[j]
        for a in range(3):
            for c in range(span[j, 2 * a], span[j, 2 * a + 1]):
                dx, dy = x[j, 0] - points[c, 0], x[j, 1] - points[c, 1]
                e = dx * dx + dy * dy
                if e <= r2:
                    k[n], d2[n] = c, e
                    n += 1
    return start, k, d2


def count_within(x, grid: CellGrid, radius: float) -> np.ndarray:
    """How many of the grid's points lie within ``radius`` (at most its h) of each row of x."""
    return np.diff(pairs_within(x, *grid.arrays(), radius)[0])


@njit(cache=True)
def nearest_within(x, points, index, keys, ox, oy, h, nx, ny, bound):
    """Each row of x's nearest point closer than ``bound`` (at most the grid's h): its input index and
    distance, or -1 and inf. Ties go to the smaller input index."""
    start, k, d2 = pairs_within(x, points, index, keys, ox, oy, h, nx, ny, bound)
    near = np.full(x.shape[0], -1, dtype=np.int64)
    dist = np.full(x.shape[0], np.inf)
    for j in range(x.shape[0]):
        best, arg = np.inf, -1
        for n in range(start[j], start[j + 1]):
            d = np.sqrt(d2[n])
            if d < best or (d == best and index[k[n]] < arg):
                best, arg = d, index[k[n]]
        if best < bound:
            near[j], dist[j] = arg, best
    return near, dist
