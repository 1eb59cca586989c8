"""The exhaustive maximum-likelihood detector: could any matcher have merged this pair?

A reference, not a matcher: it is told the true noise σ and the layout's
prior, searches every rotation and translation on a grid, and is far slower
than the matchers. Its success rate is the limit curve the matchers are
compared with.

Model. Map q's landmarks are brought into p's frame by a candidate rigid
motion, ``x_j = R(θ)ᵀ (q_j - t)``. Under "related" each x_j inside p's
convex hull is, with prior π, a landmark p also holds, observed as
``N(p_i, s² I)`` around one of them (``s² = 2σ²``, both maps' noise), and
otherwise an unshared landmark, uniform at p's density λ. Under
"unrelated" every x_j is uniform. The log-likelihood ratio is

    Λ(θ, t) = Σ_{j inside} log(1 - π + (π / λ) Σ_i N(x_j - p_i; 0, s² I)),

and the detector's statistic is its maximum over (θ, t). When at most one p
landmark lies within a few s of each x_j (landmark spacing >> s, true below
the SNRs where every matcher already succeeds), Λ separates into
``n_inside · log(1 - π)`` plus a saturating bump ``log(1 + c N_ij)`` per
landmark pair, ``c = π / ((1 - π) λ)``. So on a grid:

1. rotations of step ``s / R`` (R the largest distance of a p landmark from
   p's centroid), translations on cells ``GRID_STEP · s`` wide;
2. at each rotation every landmark pair's translation spreads the bump
   (cut at ``KERNEL_SIGMAS`` s) over the cells around it, and the q
   landmarks inside p's hull are counted at every cell, row by row (the
   hull is convex: each q landmark is inside over one interval of a row);
3. each rotation's best cell is scored by the exact Λ, and the
   ``GRID_PEAKS`` best are refined by EM (responsibilities, then a weighted
   closed-form fit, ``EM_ROUNDS`` times) and scored again.

The statistic is then compared with a threshold measured on unrelated pairs
(the experiment ``experiments.detector`` does so on its own tuning seeds).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from ._validation import check_points, check_sigma
from .alignment import rotate
from .neighbours import CellGrid, cell_grids, njit, pairs_within, ragged_starts, stacked_grids

#: Translation cells, in units of s.
GRID_STEP = 0.5
#: The bump is cut this many s from its pair's translation on the grid.
KERNEL_SIGMAS = 3.5
#: Grid points refined (the best ones, at distinct rotations).
GRID_PEAKS = 8
#: EM rounds of each refinement.
EM_ROUNDS = 10
#: Exact Λ counts p landmarks within this many s of a mapped q landmark.
EXACT_RADIUS = 5.0
#: Quadrature of ``null_log_tail``: radial (Gauss-Legendre) and angular nodes
#: per landmark disc, and at most this many landmark discs (every k-th).
QUAD_RADIAL, QUAD_ANGLES, QUAD_MAX_CENTRES = 8, 16, 400
#: Values of Chernoff's λ tried (log-spaced in [0.02, 20]).
CHERNOFF_POINTS = 40
#: Largest grid searched: translation cells per axis (each rotation rasterises a square this wide, a few
#: arrays of 8-byte cells) and rotations x cells in all (the time). The grid is set by the maps' extents in
#: units of s, so a small σ (a high SNR) or maps in different units would otherwise ask for any size:
#: beyond these the detector refuses. The paper's 100-landmark maps need 497 cells and 9.4e7 in all at
#: 17.5 dB, 2,077 and 6.9e9 at 30 dB.
MAX_GRID_SIDE = 2560
MAX_GRID_CELLS = 2**33


def inside_hull(hull: ConvexHull, x: np.ndarray) -> np.ndarray:
    """Which points x (m, 2) lie inside a 2-D convex hull (boundary included)."""
    return np.all(x @ hull.equations[:, :2].T + hull.equations[:, 2] <= 0, axis=1)


def pair_noise(sigma: float, cov_p=None, cov_q=None) -> float:
    """The mixture's s: per-coordinate standard deviation of p_i - x_j for a true pair.

    √2 σ for two maps of noise σ; with per-landmark covariances, from the
    median variance of each map (one s for the whole map, as the model has).
    """
    if cov_p is None:
        return float(np.sqrt(2.0) * sigma)
    var = np.median(np.trace(cov_p, axis1=1, axis2=2)) / 2 + np.median(np.trace(cov_q, axis1=1, axis2=2)) / 2
    return float(np.sqrt(var))


def bump_height(n_p: float, area: float, s: float, p_shared: float) -> float:
    """The mixture's c = π / ((1 - π) λ), λ = n_p / area p's landmark density, with N's 1 / (2π s²) folded in."""
    return p_shared / ((1 - p_shared) * n_p / area * 2 * np.pi * s**2)


def max_log_lr(P, Q, sigma: float, p_shared: float, density: float):
    """The exhaustive detector's statistic: max over (θ, t) of the log-likelihood ratio Λ.

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
        The two maps.
    sigma : float
        The true per-coordinate noise of one landmark, > 0.
    p_shared : float
        Prior π that a q landmark inside p's hull is common, in (0, 1).
    density : float
        Landmarks of p per unit area, > 0.

    Returns
    -------
    log_lr : float
        The maximum of Λ found.
    theta : float
    t : (2,) ndarray
        Where: ``q ≈ R(θ) p + t``.

    Raises
    ------
    ValueError
        On an invalid map (P needs 3 distinct points not all on one line), ``sigma``, ``p_shared`` or
        ``density``, or maps so wide in units of σ that the grid would exceed ``MAX_GRID_SIDE`` cells
        per axis or ``MAX_GRID_CELLS`` in all.
    """
    P, Q = check_points(P, "P"), check_points(Q, "Q", min_points=1, geometry=False)
    sigma = check_sigma(sigma)
    if not (0 < p_shared < 1 and density > 0):
        raise ValueError(f"p_shared must lie in (0, 1) and density be > 0, got {p_shared!r} and {density!r}")
    s = np.sqrt(2.0) * sigma
    n_theta, side = _grid_shape(P, Q, s)
    if side > MAX_GRID_SIDE or n_theta * side**2 > MAX_GRID_CELLS:
        raise ValueError(f"the maps span {side:.3g} grid cells of {GRID_STEP:g}·√2·sigma per axis and need "
                         f"{n_theta:.3g} rotations; at most {MAX_GRID_SIDE} cells per axis and "
                         f"{MAX_GRID_CELLS:.3g} in all are searched (are sigma and both maps in the same units?)")
    c = bump_height(density, 1.0, s, p_shared)
    model = Mixture.of_map(P, s, c, p_shared)
    theta, t = _grid_peaks(Q, model)
    best = (-np.inf, 0.0, np.zeros(2))
    for th, tt in zip(theta, t):
        th, tt = model.em(Q, th, tt)
        value = model.log_lr(Q, th, tt)[0]
        if value > best[0]:
            best = (value, th, tt)
    return best


@dataclass(frozen=True)
class Mixture:
    """The mixture model of map p (module docstring) at pair noise s, bump height c and prior π.

    Attributes
    ----------
    P : (n_p, 2) ndarray
    hull : scipy.spatial.ConvexHull
        P's convex hull.
    s, c, p_shared : float
    grid : neighbours.CellGrid
        P on cells ``EXACT_RADIUS`` s wide: every pair the model weighs.
    """

    P: np.ndarray
    hull: ConvexHull
    s: float
    c: float
    p_shared: float
    grid: CellGrid

    @classmethod
    def of_map(cls, P, s: float, c: float, p_shared: float, hull: ConvexHull | None = None) -> "Mixture":
        """The model of map P (valid input); ``hull``: P's convex hull, when the caller has it."""
        return cls.of_maps(P[None], [s], [c], p_shared, [ConvexHull(P) if hull is None else hull])[0]

    @classmethod
    def of_maps(cls, P, s, c, p_shared: float, hulls) -> list["Mixture"]:
        """``of_map`` of B maps of one size at once: P (B, n, 2), s and c one per map, their hulls."""
        # Cells a hair wider than the radius: the quadrature's cover count reaches just beyond it.
        grids = cell_grids(P, [EXACT_RADIUS * s_b * (1 + 1e-9) for s_b in s])
        return [cls(P[b], hulls[b], float(s[b]), float(c[b]), float(p_shared), grids[b]) for b in range(len(P))]

    def log_lr(self, Q, theta: float, t) -> tuple[float, int]:
        """Λ at one transform, with p's landmarks within ``EXACT_RADIUS`` s, and the number of
        mapped q landmarks inside p's hull."""
        g, n_inside = _mapped_log_terms(Q, float(theta), float(t[0]), float(t[1]), self.hull.equations,
                                        self.s, self.c, EXACT_RADIUS * self.s, *self.grid.arrays())
        return float(n_inside * np.log(1 - self.p_shared) + g), int(n_inside)

    def em(self, Q, theta: float, t) -> tuple[float, np.ndarray]:
        """EM from (θ, t): responsibilities of each (i, j), then the weighted closed-form fit.

        Returns the refined ``(theta, t)`` after ``EM_ROUNDS`` rounds (fewer when
        under two pairs lie within ``EXACT_RADIUS`` s, or once a round returns
        its input exactly: every further round would too).
        """
        theta, tx, ty = _em_rounds(Q, float(theta), float(t[0]), float(t[1]), self.hull.equations, self.s, self.c,
                                   EXACT_RADIUS * self.s, EM_ROUNDS, *self.grid.arrays())
        return theta, np.array([tx, ty])

    def null_log_tail(self, log_lr, n_inside) -> np.ndarray:
        """Upper bounds on log P(Λ >= log_lr) at one fixed transform when the maps are unrelated.

        Under "unrelated", the ``n_inside`` mapped q landmarks are independent
        and uniform over p's hull, so Λ is a sum of independent terms
        ``log(1 - π) + g(x)``, ``g(x) = log(1 + c Σ_i exp(-|x - p_i|² / 2s²))``,
        and Chernoff's bound ``P(Σ g >= L') <= exp(n K(λ) - λ L')`` holds for
        every λ > 0, with ``K(λ) = log E[exp(λ g(x))]`` over x uniform in the hull.
        g vanishes beyond a few s of every p landmark, so the expectation is
        ``1 + (1/A) ∫ (e^{λ g} - 1)``, integrated on a polar grid of
        ``QUAD_RADIAL x QUAD_ANGLES`` nodes in the disc of radius
        ``EXACT_RADIUS`` s around each p landmark (a node's weight shared among
        the discs covering it; nodes outside the hull dropped). Quadrature, not
        sampling: no randomness, and no peak is missed however small s is.

        Parameters
        ----------
        log_lr, n_inside : (H,) array_like
            Λ of H transforms and the number of mapped q landmarks inside p's hull at each.

        Returns
        -------
        (H,) ndarray
            The bounds (<= 0).
        """
        P, s, hull, radius = self.P, self.s, self.hull, EXACT_RADIUS * self.s
        radial, w_r, circle, lam = _quadrature_constants()
        rho = radius * (radial + 1) / 2
        offsets = (rho[:, None, None] * circle[None]).reshape(-1, 2)
        # ∫ f r dr dφ: Gauss-Legendre in r on [0, R] (Jacobian R/2), the trapezoid rule in φ.
        area = np.repeat(w_r * rho * radius / 2, QUAD_ANGLES) * 2 * np.pi / QUAD_ANGLES
        centres = P[::max(1, len(P) // QUAD_MAX_CENTRES)]
        x = (centres[:, None, :] + offsets[None]).reshape(-1, 2)
        weight = np.tile(area, len(centres)) * len(P) / len(centres)
        keep = inside_hull(hull, x)
        x, weight = x[keep], weight[keep]
        # A node lies in the discs of `cover` landmarks: its weight is shared among them (a partition of
        # unity over every landmark's disc, so a subsample of centres, scaled up, is unbiased).
        bumps, cover = _bumps_and_cover(x, s, radius, radius * (1 + 1e-9), *self.grid.arrays())
        g = np.log1p(self.c * bumps)
        weight = weight / (cover * hull.volume)
        # log E[e^{λ g}] = log((1 - Σw) + Σ w e^{λ g}), summed from its largest term: e^{λ g} overflows at high SNR.
        top = lam * g.max(initial=0.0)
        log_mgf = top + np.log(np.exp(lam[:, None] * g - top[:, None]) @ weight
                               + max(0.0, 1.0 - weight.sum()) * np.exp(-top))
        excess = np.asarray(log_lr, float) - np.asarray(n_inside, float) * np.log(1 - self.p_shared)
        bound = np.asarray(n_inside, float)[:, None] * log_mgf - lam * excess[:, None]
        return np.minimum(0.0, bound.min(axis=1))


@dataclass(frozen=True)
class Mixtures:
    """Mixture models of several maps, their grids and hulls stacked for the compiled kernels: EM and Λ
    of many transforms, each under its own model, in one call (the same bits as ``Mixture.em`` and
    ``Mixture.log_lr`` one at a time)."""

    models: tuple
    arrays: tuple  # the kernels' per-model arguments: hulls, s, c, radius and ``stacked_grids``

    @classmethod
    def of(cls, models) -> "Mixtures":
        models = tuple(models)
        equations = [m.hull.equations for m in models]
        arrays = (np.concatenate(equations), ragged_starts(equations),
                  np.array([m.s for m in models]), np.array([m.c for m in models]),
                  np.array([EXACT_RADIUS * m.s for m in models]), *stacked_grids([m.grid for m in models]))
        return cls(models, arrays)

    def em(self, Q, model, theta, t) -> tuple[np.ndarray, np.ndarray]:
        """``Mixture.em`` of transform k (θ (H,), t (H, 2)) under model ``model[k]`` against ``Q[model[k]]``
        (Q (M, n_q, 2), one map per model): (θ (H,), t (H, 2))."""
        theta, tx, ty = _em_batch(Q, np.asarray(model, dtype=np.int64), np.asarray(theta, dtype=float),
                                  np.ascontiguousarray(t[:, 0], dtype=float),
                                  np.ascontiguousarray(t[:, 1], dtype=float), EM_ROUNDS, *self.arrays)
        return theta, np.stack([tx, ty], axis=1)

    def log_lr(self, Q, model, theta, t) -> tuple[np.ndarray, np.ndarray]:
        """``Mixture.log_lr`` of transform k under model ``model[k]`` against ``Q[model[k]]``:
        (Λ (H,), n_inside (H,))."""
        model = np.asarray(model, dtype=np.int64)
        g, n_inside = _log_terms_batch(Q, model, np.asarray(theta, dtype=float),
                                       np.ascontiguousarray(t[:, 0], dtype=float),
                                       np.ascontiguousarray(t[:, 1], dtype=float), *self.arrays)
        # log(1 - π) as the one-model call computes it (numpy's scalar log).
        log_miss = np.array([np.log(1 - m.p_shared) for m in self.models])
        return n_inside * log_miss[model] + g, n_inside


@njit(cache=True)
def _em_batch(Q, model, theta, tx, ty, rounds, equations, eq_start, s, c, radius, points, index, keys, g_start,
              ox, oy, h, nx, ny):
    """``_em_rounds`` of each transform under its model (``Mixtures.em``)."""
    out_theta, out_tx, out_ty = np.empty(len(theta)), np.empty(len(theta)), np.empty(len(theta))
    for a in range(len(theta)):
        m = model[a]
        lo, hi = g_start[m], g_start[m + 1]
        out_theta[a], out_tx[a], out_ty[a] = _em_rounds(
            Q[m], theta[a], tx[a], ty[a], equations[eq_start[m]:eq_start[m + 1]], s[m], c[m], radius[m], rounds,
            points[lo:hi], index[lo:hi], keys[lo:hi], ox[m], oy[m], h[m], nx[m], ny[m])
    return out_theta, out_tx, out_ty


@njit(cache=True)
def _log_terms_batch(Q, model, theta, tx, ty, equations, eq_start, s, c, radius, points, index, keys, g_start,
                     ox, oy, h, nx, ny):
    """``_mapped_log_terms`` of each transform under its model (``Mixtures.log_lr``)."""
    g, n_inside = np.empty(len(theta)), np.empty(len(theta), dtype=np.int64)
    for a in range(len(theta)):
        m = model[a]
        lo, hi = g_start[m], g_start[m + 1]
        g[a], n_inside[a] = _mapped_log_terms(
            Q[m], theta[a], tx[a], ty[a], equations[eq_start[m]:eq_start[m + 1]], s[m], c[m], radius[m],
            points[lo:hi], index[lo:hi], keys[lo:hi], ox[m], oy[m], h[m], nx[m], ny[m])
    return g, n_inside


@functools.cache
def _quadrature_constants() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``null_log_tail``'s fixed arrays, computed once (numpy takes about 0.2 ms for them a call):
    Gauss-Legendre nodes and weights on [-1, 1], the ``QUAD_ANGLES`` unit directions (cos φ, sin φ), and
    the values of Chernoff's λ (any λ gives a bound: a coarse grid only loosens the best one slightly)."""
    radial, w_r = np.polynomial.legendre.leggauss(QUAD_RADIAL)
    phi = 2 * np.pi * np.arange(QUAD_ANGLES) / QUAD_ANGLES
    constants = radial, w_r, np.stack([np.cos(phi), np.sin(phi)], -1), np.geomspace(0.02, 20.0, CHERNOFF_POINTS)
    for array in constants:
        array.flags.writeable = False  # shared by every call
    return constants


@njit(cache=True)
def _inside(x, y, equations):
    """Whether (x, y) lies inside a 2-D hull given by its facet equations (boundary included)."""
    for f in range(equations.shape[0]):
        if equations[f, 0] * x + equations[f, 1] * y + equations[f, 2] > 0:
            return False
    return True


@njit(cache=True)
def _mapped_inside(Q, theta, tx, ty, equations):
    """q's landmarks brought into p's frame, ``R(θ)ᵀ (q_j - t)``, that fall inside p's hull, and their j."""
    c, s = np.cos(theta), np.sin(theta)
    x = np.empty((Q.shape[0], 2))
    j = np.empty(Q.shape[0], dtype=np.int64)
    m = 0
    for k in range(Q.shape[0]):
        dx, dy = Q[k, 0] - tx, Q[k, 1] - ty
        u, v = c * dx + s * dy, c * dy - s * dx
        if _inside(u, v, equations):
            x[m, 0], x[m, 1], j[m] = u, v, k
            m += 1
    return x[:m], j[:m]


@njit(cache=True)
def bump_sums(x, s, radius, points, index, keys, ox, oy, h, nx, ny):
    """Σ_i exp(-|x_j - p_i|² / 2s²) over the grid's points within ``radius`` of each x_j."""
    return _bumps_and_cover(x, s, radius, radius, points, index, keys, ox, oy, h, nx, ny)[0]


@njit(cache=True)
def _bumps_and_cover(x, s, radius, cover_radius, points, index, keys, ox, oy, h, nx, ny):
    """``bump_sums`` within ``radius`` and the count of the grid's points within ``cover_radius`` (>= radius)
    of each x_j, from one neighbour search (the null tail's quadrature needs both at every node)."""
    start, _, d2 = pairs_within(x, points, index, keys, ox, oy, h, nx, ny, cover_radius)
    out = np.zeros(x.shape[0])
    for j in range(x.shape[0]):
        for n in range(start[j], start[j + 1]):
            if d2[n] <= radius * radius:
                out[j] += np.exp(-d2[n] / (2 * s * s))
    return out, np.diff(start)


@njit(cache=True)
def _mapped_log_terms(Q, theta, tx, ty, equations, s, c, radius, points, index, keys, ox, oy, h, nx, ny):
    """Σ_j log(1 + c Σ_i N_ij) over the mapped q landmarks inside p's hull, and their number."""
    x, _ = _mapped_inside(Q, theta, tx, ty, equations)
    mix = bump_sums(x, s, radius, points, index, keys, ox, oy, h, nx, ny)
    return np.sum(np.log1p(c * mix)), x.shape[0]


@njit(cache=True)
def _em_rounds(Q, theta, tx, ty, equations, s, c, radius, rounds, points, index, keys, ox, oy, h, nx, ny):
    """``Mixture.em``'s rounds: each pair (i, j) within ``radius`` weighs w_ij = c N_ij / (1 + c Σ_i N_ij)
    in the weighted closed-form fit of p_i onto q_j."""
    for _ in range(rounds):
        x, js = _mapped_inside(Q, theta, tx, ty, equations)
        start, k, d2 = pairs_within(x, points, index, keys, ox, oy, h, nx, ny, radius)
        if len(k) < 2:
            break
        w = c * np.exp(-d2 / (2 * s * s))
        for u in range(x.shape[0]):
            # Summed and divided in place: a slice's ``/=`` allocates, once per landmark.
            total = 0.0
            for n in range(start[u], start[u + 1]):
                total += w[n]
            for n in range(start[u], start[u + 1]):
                w[n] /= 1 + total
        # The weighted means, then the centred cross and dot sums.
        total, ma0, ma1, mb0, mb1 = 0.0, 0.0, 0.0, 0.0, 0.0
        for u in range(x.shape[0]):
            for n in range(start[u], start[u + 1]):
                total += w[n]
                ma0, ma1 = ma0 + w[n] * points[k[n], 0], ma1 + w[n] * points[k[n], 1]
                mb0, mb1 = mb0 + w[n] * Q[js[u], 0], mb1 + w[n] * Q[js[u], 1]
        ma0, ma1, mb0, mb1 = ma0 / total, ma1 / total, mb0 / total, mb1 / total
        cross, dot = 0.0, 0.0
        for u in range(x.shape[0]):
            q0, q1 = Q[js[u], 0] - mb0, Q[js[u], 1] - mb1
            for n in range(start[u], start[u + 1]):
                p0, p1 = points[k[n], 0] - ma0, points[k[n], 1] - ma1
                cross += w[n] * (p0 * q1 - p1 * q0)
                dot += w[n] * (p0 * q0 + p1 * q1)
        new = np.arctan2(cross, dot)
        cn, sn = np.cos(new), np.sin(new)
        new_tx, new_ty = mb0 - (cn * ma0 - sn * ma1), mb1 - (sn * ma0 + cn * ma1)
        if new == theta and new_tx == tx and new_ty == ty:
            break
        theta, tx, ty = new, new_tx, new_ty
    return theta, tx, ty


def _grid_shape(P, Q, s) -> tuple[float, float]:
    """Rotations and translation cells per axis of ``_grid_peaks``'s grid (floats: they may be huge)."""
    reach = np.sqrt(np.max(np.sum((P - P.mean(axis=0)) ** 2, axis=1)))
    reach_q = np.sqrt(np.max(np.sum((Q - Q.mean(axis=0)) ** 2, axis=1)))
    h = GRID_STEP * s
    return float(np.ceil(2 * np.pi * reach / s)), float(2 * (np.ceil(reach_q / h) + np.ceil(reach / h)) + 1)


def _grid_peaks(Q, model: Mixture):
    """The ``GRID_PEAKS`` best (θ, t) of the grid, at distinct rotations.

    Per rotation, the pair translations are counted on cells ``GRID_STEP·s``
    wide and spread over the bump's cells, the q landmarks inside p's hull
    are counted at every cell (``_grid_best_cells``), and the best cell is
    kept; these are ranked by their exact Λ.
    """
    P, s, c, p_shared = model.P, model.s, model.c, model.p_shared
    pm, qm = P.mean(axis=0), Q.mean(axis=0)
    pc, qc = P - pm, Q - qm
    reach = np.sqrt(np.max(np.sum(pc**2, axis=1)))
    reach_q = np.sqrt(np.max(np.sum(qc**2, axis=1)))
    n_theta = int(np.ceil(2 * np.pi * reach / s))
    thetas = 2 * np.pi * np.arange(n_theta) / n_theta
    h = GRID_STEP * s
    K = int(np.ceil(KERNEL_SIGMAS / GRID_STEP))
    off = h * np.arange(-K, K + 1)
    kernel = np.log1p(c * np.exp(-(off[:, None] ** 2 + off[None, :] ** 2) / (2 * s**2)))
    Ka, Kb = int(np.ceil(reach_q / h)), int(np.ceil(reach / h))
    # Translations reach at most reach + reach_q: cells -M..M hold them all.
    M = Ka + Kb
    # q's landmarks on their grid cells, for counting those inside p's hull at a translation.
    hull_c = ConvexHull(pc)
    u = np.rint(qc / h).astype(np.int64) + Ka
    best_cell = _grid_best_cells(pc, qc, thetas, h, M, kernel, np.log(1 - p_shared), hull_c.equations, u, Kb)
    # Back to the maps' own frames: q = R p + t with t = qm + t_centred - R pm.
    ts = qm + (best_cell - M) * h - rotate(thetas, pm[None])[:, 0]
    exact = np.array([model.log_lr(Q, th, t)[0] for th, t in zip(thetas, ts)])
    order = np.argsort(-exact, kind="stable")[:GRID_PEAKS]
    return thetas[order], ts[order]


@njit(cache=True)
def _hull_rows(Kb, h, c, s, equations):
    """p's centred hull rotated by -θ on the grid of cells (vx, vy), 0..2 Kb each, cell centres
    ``h (v - Kb)``: the range ``lo[vx] .. hi[vx]`` of vy inside it on each row (empty when lo > hi)."""
    lo, hi = np.zeros(2 * Kb + 1, dtype=np.int64), np.full(2 * Kb + 1, 2 * Kb, dtype=np.int64)
    for vx in range(2 * Kb + 1):
        gx = h * (vx - Kb)
        for f in range(equations.shape[0]):
            # The facet's test on the rotated cell centre, e0 (c gx + s gy) + e1 (c gy - s gx) + e2 <= 0,
            # is linear in gy: a gy + b <= 0.
            a = equations[f, 0] * s + equations[f, 1] * c
            b = (equations[f, 0] * c - equations[f, 1] * s) * gx + equations[f, 2]
            if a > 0:
                hi[vx] = min(hi[vx], np.int64(np.floor(Kb + (-b / a) / h)))
            elif a < 0:
                lo[vx] = max(lo[vx], np.int64(np.ceil(Kb + (-b / a) / h)))
            elif b > 0:
                lo[vx], hi[vx] = 1, 0
    return lo, hi


@njit(cache=True)
def _grid_best_cells(pc, qc, thetas, h, M, kernel, log_miss, equations, u, Kb):
    """Per rotation, the cell of the largest ``Σ bump + log(1 - π) · n_inside`` (the first of ties).

    The bump sum is spread from each landmark pair's translation cell over the kernel's cells. q landmark
    j (on its grid cell ``u[j]``) lies inside p's hull at translation cells (mx, my) that form, row by row,
    one interval of my (the hull is convex, ``_hull_rows``): counted by differences along each row.
    """
    side, K = 2 * M + 1, (kernel.shape[0] - 1) // 2
    value = np.empty((side, side))
    count = np.empty((side, side + 1), dtype=np.int64)
    best_cell = np.zeros((len(thetas), 2), dtype=np.int64)
    for a in range(len(thetas)):
        c, s = np.cos(thetas[a]), np.sin(thetas[a])
        value[:] = 0.0
        count[:] = 0
        for i in range(pc.shape[0]):
            rx, ry = c * pc[i, 0] - s * pc[i, 1], s * pc[i, 0] + c * pc[i, 1]
            for j in range(qc.shape[0]):
                cx = np.int64(np.rint((qc[j, 0] - rx) / h)) + M
                cy = np.int64(np.rint((qc[j, 1] - ry) / h)) + M
                for dx in range(max(-K, -cx), min(K, side - 1 - cx) + 1):
                    for dy in range(max(-K, -cy), min(K, side - 1 - cy) + 1):
                        value[cx + dx, cy + dy] += kernel[dx + K, dy + K]
        lo, hi = _hull_rows(Kb, h, c, s, equations)
        for j in range(u.shape[0]):
            # Cell m puts q_j at hull cell v = 2 Kb + u_j - m.
            for vx in range(2 * Kb + 1):
                mx = 2 * Kb + u[j, 0] - vx
                if 0 <= mx < side and lo[vx] <= hi[vx]:
                    first, last = max(2 * Kb + u[j, 1] - hi[vx], 0), min(2 * Kb + u[j, 1] - lo[vx], side - 1)
                    if first <= last:
                        count[mx, first] += 1
                        count[mx, last + 1] -= 1
        best, arg = -np.inf, 0
        for mx in range(side):
            inside = 0
            for my in range(side):
                inside += count[mx, my]
                v = value[mx, my] + log_miss * inside
                if v > best:
                    best, arg = v, mx * side + my
        best_cell[a, 0], best_cell[a, 1] = arg // side, arg % side
    return best_cell
