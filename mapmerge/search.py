"""Global transform search: merging where triangles stop discriminating.

Below about 17 dB the noise distorts triangles as much as the differences
between them, so triangle matching finds nothing, yet the maps still hold
the transform: many weak coincidences add up. ``search_pairs`` finds it
without any correspondence:

1. Rotations on a grid of step ``r / R`` (``r`` the pair noise: the
   standard deviation per coordinate of p_i - x_j for a true pair, √2σ;
   ``R`` the largest distance of a p landmark from p's centroid), so a grid
   rotation is within ``r / 2`` of the true one at every landmark.
2. At each rotation every landmark pair (i, j) votes for the translation
   ``t = q_j - R(θ) p_i``, counted on a grid of cells ``r`` wide summed
   over 2 x 2 windows; the fullest windows over all rotations are the
   hypotheses (``N_PEAKS``, at distinct rotations).
3. Each hypothesis is refined: nearest-neighbour pairs, refitted with the
   n-point closed form, the pairing radius halved each round from the vote
   cell's down to 2r (``REFINE_ROUNDS``), then by EM on the mixture model of
   ``mapmerge.exhaustive`` (every q landmark inside p's hull is, with prior
   ``MIXTURE_PRIOR``, a noisy copy of some p landmark, otherwise anywhere).
4. Acceptance is a contrario on that model's log-likelihood ratio Λ: for a
   fixed transform, unrelated maps put q's landmarks uniformly over p's
   hull, and ``exhaustive.Mixture.null_log_tail`` bounds P(Λ >= observed) by
   Chernoff's inequality, computed from p's own landmarks (no tuning, no
   sampling). With H the number of (rotation, translation) hypotheses at
   resolution r, ``NFA = H · P(Λ >= observed)``, and the best hypothesis is
   accepted when NFA <= ``SEARCH_NFA``; its landmarks are then associated
   (``association.associate_batch``, every map pair of a batch at once).
   Λ pools the evidence of every landmark, weighed by how close it lies to
   its partner, which no single landmark carries at 10 dB, where a chance
   partner lies within the noise of most landmarks.
   Where the noise exceeds ``MAX_NOISE_SPACING`` landmark spacings (about
   0-2.5 dB) the bound fails over the search as a whole, and the maps hold
   no transform a search could find: the search then declines.

The search costs O(n_θ n_p n_q): on maps above ``MAX_SEARCH_LANDMARKS``
landmarks the votes use about that many per map, the ones whose distance
to their ``THIN_RANK``-th nearest neighbour is a local maximum
(``_thinned``). That choice depends on the map's shape only, not its frame,
so both maps mostly pick the same common landmarks, and the thinned maps'
spacing is so much wider than the noise that their votes are as clean as
at a far higher SNR. Each hypothesis is refined on the thinned maps first
(whose spacing tolerates the coarse cell's error), then on the full maps;
the test uses every landmark (its quadrature on at most
``exhaustive.QUAD_MAX_CENTRES`` landmark discs). 10⁴-landmark maps at
15 dB merge in about 3 s.

The vote grid spans both maps' reach, so maps of very different extents
(one in millimetres, the other in metres) would need a grid of any size:
it has at most ``MAX_VOTE_CELLS`` cells per axis (wider cells beyond), and
only the cells holding votes are scored, so the search's memory and time
depend on the landmark counts alone, never on the coordinates.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from .alignment import Alignment, fit_transforms
from .association import associate_batch, covariance_rows, declared_triangles_batch
from .exhaustive import Mixture, Mixtures, bump_height, pair_noise
from .neighbours import cell_grids, nearest_within, njit, ragged_starts, stacked_grids
from .result import MergeBatch, build_batch
from .triangles import PARALLEL_MIN_LANDMARKS, MapHulls, TriangleBatch

#: Hypotheses refined (the fullest translation windows, at distinct rotations).
N_PEAKS = 8
#: Prior π of the mixture model that refines and tests a hypothesis: neutral
#: (log-odds 0). The test is calibrated by its own null tail for any fixed π,
#: so this is part of the statistic, not a guess at the overlap.
MIXTURE_PRIOR = 0.5
#: Nearest-neighbour refit rounds of a hypothesis before the association.
REFINE_ROUNDS = 4
#: A match is accepted when its number of false alarms is at most this: an
#: unrelated pair of maps passes with probability at most about this at a
#: fixed transform (tuning: docs/tuning.md).
SEARCH_NFA = 1e-4
#: The search declines when the pair noise r exceeds this many landmark
#: spacings of p (``sqrt(hull area / n_p)``): every q landmark then has a
#: chance partner within the noise, and the bound of step 4 no longer holds
#: over the search as a whole (where that happened on tuning pairs: docs/tuning.md).
MAX_NOISE_SPACING = 0.6
#: Landmarks per map used to vote; larger maps vote with about this many (``_thinned``).
MAX_SEARCH_LANDMARKS = 300
#: Larger maps vote with the landmarks whose distance to their ``THIN_RANK``-th
#: nearest neighbour is largest in their neighbourhood: a choice that depends on
#: the map's shape only, so the two maps mostly choose the same common landmarks.
THIN_RANK = 3
#: Nearest neighbours every landmark is first compared with in ``_thinned`` (speed only).
THIN_PREFILTER = 16
#: Coarsest vote cell, in landmark spacings (√(hull area / n) of p).
COARSE_SPACING = 0.3
#: Largest rotation grid (a finer step than this needs is not searched).
MAX_ROTATIONS = 1440
#: Largest translation vote grid, in cells per axis. The grid spans both maps' reach, so two maps in
#: different units (one 1,000x the other's extent) would need a grid a million times a same-unit pair's;
#: beyond this the cells are widened instead (cost then depends on the landmark counts alone). Same-unit
#: maps of similar extent need a few hundred (about 160 for two 300-landmark maps of one area).
MAX_VOTE_CELLS = 2048


def _thinned(X: np.ndarray, m: int) -> np.ndarray:
    """About m of X's landmarks, chosen the same way in any frame: local maxima of the distance to the
    ``THIN_RANK``-th nearest neighbour among each landmark's ``len(X) / m`` nearest (all of X when <= m)."""
    if len(X) <= m:
        return X
    tree = cKDTree(X)
    k = max(2, round(len(X) / m))
    # Most landmarks lose to one of their nearest few already, so only those that beat their
    # ``THIN_PREFILTER`` nearest are checked against all k (the same landmarks: the nearest few are among the
    # nearest k); at 10⁵ landmarks this takes 0.2 s a map instead of 3.8 s.
    first = min(k, THIN_PREFILTER)
    workers = -1 if len(X) >= PARALLEL_MIN_LANDMARKS else 1
    dist, near = tree.query(X, k=max(first, THIN_RANK) + 1, workers=workers)
    rank = dist[:, THIN_RANK]
    (alive,) = np.nonzero(np.all(rank[:, None] >= rank[near[:, 1:first + 1]], axis=1))
    if k > THIN_PREFILTER:
        neighbours = tree.query(X[alive], k=k + 1, workers=workers)[1][:, 1:]
        alive = alive[np.all(rank[alive, None] >= rank[neighbours], axis=1)]
    return X[alive]


@njit(cache=True)
def _centres(X, start):
    """Each part's centroid (numpy's ``mean(axis=0)``: its rows summed in order) and the largest squared
    distance of its rows from it."""
    K = len(start) - 1
    centre, far = np.empty((K, 2)), np.zeros(K)
    for k in range(K):
        a, b = start[k], start[k + 1]
        sx, sy = X[a, 0], X[a, 1]
        for i in range(a + 1, b):
            sx += X[i, 0]
            sy += X[i, 1]
        centre[k, 0], centre[k, 1] = sx / (b - a), sy / (b - a)
        for i in range(a, b):
            dx, dy = X[i, 0] - centre[k, 0], X[i, 1] - centre[k, 1]
            far[k] = max(far[k], dx * dx + dy * dy)
    return centre, far


def _hypotheses(Ps, Qs, r: np.ndarray, area: np.ndarray):
    """Coarse search of K map pairs (lists of maps Ps, Qs; ``area``: each P's hull area): the fullest (θ, t)
    vote windows of each, its vote cell width, and its number of hypotheses at resolution r.

    The vote cells are ``r`` wide, or ``COARSE_SPACING`` landmark spacings
    when that is wider (low noise: a finer grid only costs time, the
    refinement finds the exact transform). The hypothesis count for the
    acceptance test is taken at resolution ``r`` whatever the grid.
    Returns (pair, θ, t) of the hypotheses, (K,) cells and (K,) counts.
    """
    p_start, q_start = ragged_starts(Ps), ragged_starts(Qs)
    Xp, Xq = np.concatenate(Ps), np.concatenate(Qs)
    pm, far_p = _centres(Xp, p_start)
    qm, far_q = _centres(Xq, q_start)
    reach = np.sqrt(far_p)
    spacing = np.sqrt(area / np.diff(p_start))
    # Translations are voted relative to q's centroid minus rotated p's centroid.
    pc = Xp - np.repeat(pm, np.diff(p_start), axis=0)
    qc = Xq - np.repeat(qm, np.diff(q_start), axis=0)
    half = reach + np.sqrt(far_q)
    # At most MAX_VOTE_CELLS cells per axis (maps of very different extents): ``2 half / cell`` then stays
    # below MAX_VOTE_CELLS - 1 whatever its rounding.
    cell = np.maximum(np.maximum(r, COARSE_SPACING * spacing), 2 * half / (MAX_VOTE_CELLS - 2))
    n_theta = np.clip(np.ceil(2 * np.pi * reach / cell), 8, MAX_ROTATIONS).astype(np.int64)
    t_start = np.concatenate([[0], np.cumsum(n_theta)])
    of_theta = np.repeat(np.arange(len(Ps)), n_theta)
    thetas = 2 * np.pi * (np.arange(t_start[-1]) - t_start[of_theta]) / n_theta[of_theta]
    n_cells = np.ceil(2 * half / cell).astype(np.int64) + 1
    best_count, best_window = _vote_peaks_batch(pc, p_start, qc, q_start, thetas, t_start, half, cell, n_cells)
    wx, wy = np.divmod(best_window, (n_cells - 1)[of_theta])
    cell_t, half_t = cell[of_theta], half[of_theta]
    best_t = np.stack([(wx + 1) * cell_t - half_t, (wy + 1) * cell_t - half_t], axis=1)
    # Each pair's N_PEAKS fullest rotations, the first of ties.
    order = np.lexsort((-best_count, of_theta))
    order = order[np.arange(order.size) - t_start[of_theta[order]] < N_PEAKS]
    pair, theta = of_theta[order], thetas[order]
    # Back to the maps' own frames: q = R p + t with t = qc_mean + t_centred - R pc_mean.
    (mx, my), c, s = pm[pair].T, np.cos(theta), np.sin(theta)
    t = qm[pair] + best_t[order] - np.stack([c * mx - s * my, s * mx + c * my], axis=1)
    with np.errstate(over="ignore"):  # inf for maps 1e100 noise widths across: then no NFA is small
        n_hypotheses = np.array([np.ceil(2 * np.pi * a / b) * np.ceil(2 * h / b) ** 2
                                 for a, h, b in zip(reach, half, r)])
    return pair, theta, t, cell, n_hypotheses


@njit(cache=True)
def _vote_peaks_batch(pc, p_start, qc, q_start, thetas, t_start, half, cell, n_cells):
    """``_vote_peaks`` of each map pair k: landmarks ``pc[p_start[k]:p_start[k + 1]]`` and q's likewise,
    rotations ``thetas[t_start[k]:t_start[k + 1]]``."""
    count, window = np.empty(len(thetas), dtype=np.int64), np.empty(len(thetas), dtype=np.int64)
    for k in range(len(half)):
        a, b = t_start[k], t_start[k + 1]
        count[a:b], window[a:b] = _vote_peaks(pc[p_start[k]:p_start[k + 1]], qc[q_start[k]:q_start[k + 1]],
                                              thetas[a:b], half[k], cell[k], n_cells[k])
    return count, window


@njit(cache=True)
def _vote_peaks(pc, qc, thetas, half, cell, n_cells):
    """Per rotation, the fullest 2 x 2 window of translation votes ``q_j - R(θ) p_i`` on cells ``cell`` wide
    (cell ``floor((t + half) / cell)``): its count and its index ``wx (n_cells - 1) + wy``, the first of ties.

    A 2 x 2 window catches a true pile-up split by a cell boundary whole. Only the windows holding a vote
    are scored, and the grid is cleared vote by vote, so a rotation costs O(n_p n_q) whatever the grid's size.
    """
    n_p, n_q = pc.shape[0], qc.shape[0]
    grid = np.zeros((n_cells, n_cells), dtype=np.int64)
    kx, ky = np.empty(n_p * n_q, dtype=np.int64), np.empty(n_p * n_q, dtype=np.int64)
    count, window = np.zeros(len(thetas), dtype=np.int64), np.zeros(len(thetas), dtype=np.int64)
    for a in range(len(thetas)):
        c, s = np.cos(thetas[a]), np.sin(thetas[a])
        m = 0
        for i in range(n_p):
            rx, ry = c * pc[i, 0] - s * pc[i, 1], s * pc[i, 0] + c * pc[i, 1]
            for j in range(n_q):
                kx[m] = np.int64(np.floor((qc[j, 0] - rx + half) / cell))
                ky[m] = np.int64(np.floor((qc[j, 1] - ry + half) / cell))
                grid[kx[m], ky[m]] += 1
                m += 1
        best, arg = -1, 0
        for m in range(n_p * n_q):
            for wx in range(max(kx[m] - 1, 0), min(kx[m], n_cells - 2) + 1):
                for wy in range(max(ky[m] - 1, 0), min(ky[m], n_cells - 2) + 1):
                    v = grid[wx, wy] + grid[wx + 1, wy] + grid[wx, wy + 1] + grid[wx + 1, wy + 1]
                    f = wx * (n_cells - 1) + wy
                    if v > best or (v == best and f < arg):
                        best, arg = v, f
        for m in range(n_p * n_q):
            grid[kx[m], ky[m]] = 0
        count[a], window[a] = best, arg
    return count, window


@dataclass(frozen=True)
class _Fits:
    """Refined hypotheses: each one's map pair, transform and J*, and the landmark pairs (h, i, j) it was
    fitted on (hypothesis h, p index i and q index j within its maps)."""

    pair: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    cost: np.ndarray
    h: np.ndarray
    i: np.ndarray
    j: np.ndarray

    def alignment(self, k: int, P, Q, sigma: float) -> Alignment:
        """Hypothesis k's ``Alignment`` (P, Q: the maps it was fitted on)."""
        sel = self.h == k
        return Alignment.from_fit(float(self.theta[k]), self.t[k], self.cost[k], P[self.i[sel]], Q[self.j[sel]],
                                  sigma)


def _refine(Ps, Qs, pair, theta, t, r: np.ndarray, cell: np.ndarray) -> _Fits:
    """Each hypothesis refined: nearest-neighbour pairs, refitted, the radius halved each round from the
    coarse cell's to 2r; every hypothesis of every map pair (lists of maps Ps, Qs) at once.

    Hypotheses left with fewer than 3 pairs are dropped.
    """
    radius = [max(2 * a, 2 * b) for a, b in zip(r, cell)]
    grids = (cell_grids(np.stack(Ps), radius) if len({len(X) for X in Ps}) == 1 else
             [grid for X, a in zip(Ps, radius) for grid in cell_grids(X[None], [a])])
    p_start, q_start, stacked = ragged_starts(Ps), ragged_starts(Qs), stacked_grids(grids)
    Xp, Xq = np.concatenate(Ps), np.concatenate(Qs)
    theta, t = np.asarray(theta, float), np.asarray(t, float).reshape(-1, 2)
    for k in range(REFINE_ROUNDS):
        bound = np.array([max(2 * a, 2 * b / 2**k) for a, b in zip(r, cell)])
        fitted, h, i, j = _nearest_pairs_batch(Xq, q_start, pair, np.cos(-theta), np.sin(-theta), t, *stacked,
                                               bound, np.diff(p_start))
        pair = pair[fitted]
        theta, t, cost = fit_transforms(h, Xp[p_start[pair[h]] + i], Xq[q_start[pair[h]] + j], len(pair))
    return _Fits(pair, theta, t, cost, h, i, j)


@njit(cache=True)
def _nearest_pairs_batch(Q, q_start, pair, cos, sin, t, points, index, keys, g_start, ox, oy, h, nx, ny, bound, n_p):
    """``_nearest_pairs`` of hypotheses of many map pairs: hypothesis a of map pair ``pair[a]`` maps that
    pair's q landmarks (rows ``q_start`` of Q) onto its p grid (rows ``g_start`` of the stacked grids).

    Returns which hypotheses have at least 3 pairs and their pairs (hypothesis renumbered over those, p
    index, q index within their maps), by hypothesis, then p index.
    """
    n_h = len(cos)
    fitted = np.zeros(n_h, dtype=np.bool_)
    size = 0
    for a in range(n_h):
        size += min(n_p[pair[a]], q_start[pair[a] + 1] - q_start[pair[a]])
    out_h, out_i, out_j = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
    best_j, best_d = np.empty(n_p.max(), dtype=np.int64), np.empty(n_p.max())
    m, n_fitted = 0, 0
    for a in range(n_h):
        b = pair[a]
        Qb = Q[q_start[b]:q_start[b + 1]]
        lo, hi = g_start[b], g_start[b + 1]
        fitted_a, m_a = _nearest_pairs(Qb, cos[a], sin[a], t[a], points[lo:hi], index[lo:hi], keys[lo:hi], ox[b],
                                       oy[b], h[b], nx[b], ny[b], bound[b], n_p[b], best_j, best_d, n_fitted,
                                       out_h[m:], out_i[m:], out_j[m:])
        if fitted_a:
            fitted[a] = True
            n_fitted += 1
            m += m_a
    return fitted, out_h[:m], out_i[:m], out_j[:m]


@njit(cache=True)
def _nearest_pairs(Q, cos, sin, t, points, index, keys, ox, oy, h, nx, ny, bound, n_p, best_j, best_d, label,
                   out_h, out_i, out_j):
    """One refine round's pairs of one hypothesis (cos, sin of -θ, t): q landmark j mapped into p's frame,
    ``R(-θ)(q_j - t)``, pairs with its nearest p landmark closer than ``bound``, and each p landmark keeps its
    nearest q landmark (the first of ties). With at least 3 pairs, they are written (``label``, p index,
    q index, by p index) to the front of ``out_*``: returns (whether, how many)."""
    n_q = Q.shape[0]
    x = np.empty((n_q, 2))
    for q in range(n_q):
        dx, dy = Q[q, 0] - t[0], Q[q, 1] - t[1]
        x[q, 0], x[q, 1] = cos * dx - sin * dy, sin * dx + cos * dy
    near, dist = nearest_within(x, points, index, keys, ox, oy, h, nx, ny, bound)
    best_j[:n_p] = -1
    for q in range(n_q):
        i = near[q]
        if i >= 0 and (best_j[i] < 0 or dist[q] < best_d[i]):
            best_j[i], best_d[i] = q, dist[q]
    count = 0
    for i in range(n_p):
        count += best_j[i] >= 0
    if count < 3:
        return False, 0
    m = 0
    for i in range(n_p):
        if best_j[i] >= 0:
            out_h[m], out_i[m], out_j[m] = label, i, np.int64(best_j[i])
            m += 1
    return True, m


def _best_hypotheses(P, Q, sigma, cov_p, cov_q, hulls, nfa_level=SEARCH_NFA):
    """Steps 1-4 on B map pairs: each one's best hypothesis when its NFA is at most ``nfa_level`` (else None)
    and that NFA (inf when none could be refined, or the noise exceeds ``MAX_NOISE_SPACING`` landmark
    spacings). ``hulls``: each P's convex hull."""
    B = len(P)
    best, nfa = [None] * B, np.full(B, np.inf)
    r = np.array([pair_noise(float(sigma[b]), covariance_rows(cov_p, b),
                             covariance_rows(cov_q, b)) for b in range(B)])
    area = np.array([hull.volume for hull in hulls])
    live = np.flatnonzero(~(r > MAX_NOISE_SPACING * np.sqrt(area / P.shape[1])))
    if live.size == 0:
        return best, nfa
    # Larger maps vote and are first refined on about MAX_SEARCH_LANDMARKS landmarks each.
    thin = max(P.shape[1], Q.shape[1]) > MAX_SEARCH_LANDMARKS
    Ps = [_thinned(P[b], MAX_SEARCH_LANDMARKS) for b in live] if thin else list(P[live])
    Qs = [_thinned(Q[b], MAX_SEARCH_LANDMARKS) for b in live] if thin else list(Q[live])
    area_s = np.array([ConvexHull(X).volume for X in Ps]) if thin else area[live]
    pair, theta, t, cell, n_hyp = _hypotheses(Ps, Qs, r[live], area_s)
    fits = _refine(Ps, Qs, pair, theta, t, r[live], cell)
    if thin:
        # Refined on the sparse subsets first (their spacing tolerates the coarse cell's error), then on the maps.
        fits = _refine(list(P[live]), list(Q[live]), fits.pair, fits.theta, fits.t, r[live], r[live])
    if fits.pair.size == 0:
        return best, nfa
    # EM on the mixture model, then its a contrario test (module docstring, step 4).
    models = Mixtures.of(Mixture.of_maps(
        P[live], [float(r[b]) for b in live],
        [bump_height(P.shape[1], hulls[b].volume, float(r[b]), MIXTURE_PRIOR) for b in live], MIXTURE_PRIOR,
        [hulls[b] for b in live]))
    # Hypotheses often refine to the very same transform, which EM would only repeat (on large maps a
    # round costs tens of milliseconds): each distinct one is run once.
    same = np.column_stack([fits.pair, fits.theta.view(np.int64), fits.t.view(np.int64)])
    _, first, copy = np.unique(same, axis=0, return_index=True, return_inverse=True)
    theta, t = models.em(Q[live], fits.pair[first], fits.theta[first], fits.t[first])
    log_lr, n_inside = models.log_lr(Q[live], fits.pair[first], theta, t)
    copy = copy.reshape(-1)  # one index a row whatever numpy release
    theta, t, log_lr, n_inside = theta[copy], t[copy], log_lr[copy], n_inside[copy]
    bounds = np.searchsorted(fits.pair, np.arange(live.size + 1))
    for k in np.flatnonzero(np.diff(bounds)):
        sel = slice(bounds[k], bounds[k + 1])
        log_nfa = np.log(n_hyp[k]) + models.models[k].null_log_tail(log_lr[sel], n_inside[sel])
        h = bounds[k] + int(np.argmin(log_nfa))
        b = live[k]
        nfa[b] = float(np.exp(min(log_nfa[h - bounds[k]], 700.0)))
        if not log_nfa[h - bounds[k]] > np.log(nfa_level):
            best[b] = dataclasses.replace(fits.alignment(h, P[b], Q[b], float(sigma[b])), theta=float(theta[h]),
                                          t=t[h])
    return best, nfa


def search_batch(P, Q, sigma, cov_p=None, cov_q=None, hulls=None, nfa_level=SEARCH_NFA):
    """Landmark associations of B map pairs found by the global search.

    Every pair's hypotheses are searched, refined and tested together
    (steps 1-4, the compiled stages over all pairs at once); the significant
    ones are associated in one ``association.associate_batch``.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    sigma : (B,) ndarray
    cov_p, cov_q : (B, n, 2, 2) ndarray, optional
        Per-landmark covariances (the pair noise and the association use them).
    hulls : (MapHulls, MapHulls), optional
        The convex hulls of P and Q, when the caller keeps them.
    nfa_level : float, default ``SEARCH_NFA``
        A pair's best hypothesis is associated when its NFA is at most this
        (``np.inf``: every pair's, for a caller with a test of its own).

    Returns
    -------
    trial : (K,) int ndarray
        Map pair of each association (none for a pair whose best hypothesis
        is over ``nfa_level`` or associates fewer than 3 landmarks).
    pairs : (K, 2) int ndarray
        Associations (p index, q index), by map pair, then p index.
    contested : (K,) bool ndarray
    nfa : (B,) ndarray
        Number of false alarms of each pair's best hypothesis (inf when none
        could be refined, or the noise exceeds ``MAX_NOISE_SPACING`` landmark
        spacings).
    """
    B = len(P)
    hulls_p, hulls_q = (MapHulls(P), MapHulls(Q)) if hulls is None else hulls
    best, nfa = _best_hypotheses(P, Q, sigma, cov_p, cov_q, [hulls_p[b] for b in range(B)], nfa_level)
    rows = np.array([b for b, al in enumerate(best) if al is not None], dtype=np.intp)
    if rows.size == 0:
        return np.empty(0, dtype=np.intp), np.empty((0, 2), dtype=np.intp), np.empty(0, dtype=bool), nfa
    trial, pairs, contested = associate_batch(
        P[rows], Q[rows], np.array([best[b].theta for b in rows]), np.stack([best[b].t for b in rows]),
        np.stack([best[b].cov for b in rows]), np.asarray(sigma, dtype=float)[rows],
        covariance_rows(cov_p, rows), covariance_rows(cov_q, rows),
        [(hulls_p[b], hulls_q[b]) for b in rows])
    trial = rows[trial]
    keep = np.bincount(trial, minlength=B)[trial] >= 3
    return trial[keep], pairs[keep], contested[keep], nfa


def search_pairs(P, Q, sigma: float, cov_p=None, cov_q=None):
    """Landmark associations of one map pair found by the global search (``search_batch`` of one pair).

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
    sigma : float
    cov_p, cov_q : (n, 2, 2) ndarray, optional

    Returns
    -------
    pairs : (K, 2) int ndarray
        Associations (empty when no hypothesis is significant).
    contested : (K,) bool ndarray
    nfa : float
        Number of false alarms of the best hypothesis.
    """
    one = (lambda a: None if a is None else np.asarray(a)[None])
    _, pairs, contested, nfa = search_batch(np.asarray(P)[None], np.asarray(Q)[None], np.array([sigma], dtype=float),
                                            one(cov_p), one(cov_q))
    return pairs, contested, float(nfa[0])


def _digest(*parts) -> bytes:
    """A digest of arrays (None: empty), with their shapes."""
    digest = hashlib.sha256()
    for part in parts:
        part = np.empty(0) if part is None else np.ascontiguousarray(part, dtype=float)
        digest.update(repr(part.shape).encode() + part.tobytes())
    return digest.digest()


class SearchMemo:
    """``search_batch`` remembering its answers, for a caller that merges the
    same map pairs again (the harness merges each pair once per τ rule, and
    the search does not depend on τ). Each map pair is keyed by a digest of
    its inputs, and only the pairs not seen before are searched (in one
    batch); the answers are copies of the search's own arrays, so they are
    bit for bit the search's.
    """

    def __init__(self) -> None:
        self._answers: dict[bytes, tuple] = {}

    def __call__(self, P, Q, sigma, cov_p=None, cov_q=None, hulls=None, nfa_level=SEARCH_NFA):
        keys = [_digest(P[b], Q[b], np.float64(sigma[b]), covariance_rows(cov_p, b), covariance_rows(cov_q, b),
                        np.float64(nfa_level)) for b in range(len(P))]
        first = {}  # each map pair not seen before, once
        for b, key in enumerate(keys):
            if key not in self._answers:
                first.setdefault(key, b)
        new = np.array(list(first.values()), dtype=np.intp)
        if new.size:
            trial, pairs, contested, nfa = search_batch(P[new], Q[new], np.asarray(sigma)[new],
                                                        covariance_rows(cov_p, new),
                                                        covariance_rows(cov_q, new),
                                                        None if hulls is None else (hulls[0].take(new),
                                                                                    hulls[1].take(new)),
                                                        nfa_level)
            bounds = np.searchsorted(trial, np.arange(new.size + 1))
            for k, b in enumerate(new):
                sel = slice(bounds[k], bounds[k + 1])
                self._answers[keys[b]] = (pairs[sel], contested[sel], nfa[k])
        answers = [self._answers[key] for key in keys]
        trial = np.repeat(np.arange(len(P)), [len(pairs) for pairs, _, _ in answers])
        return (trial, np.concatenate([pairs for pairs, _, _ in answers]).astype(np.intp).reshape(-1, 2),
                np.concatenate([contested for _, contested, _ in answers]).astype(bool),
                np.array([nfa for _, _, nfa in answers], dtype=float))


def search_merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, cov_p=None, cov_q=None) -> MergeBatch:
    """The ``method="search"`` merge of B map pairs (``search_batch``).

    Triangles are not used to find the transform; the triangle pairs whose
    three landmarks were associated (and not contested) are reported as
    declared, with their log Λ.
    """
    trial, pairs, contested, _ = search_batch(P, Q, sigma, cov_p, cov_q, (tri_p.hulls, tri_q.hulls))
    tri_trial, tri_pairs, scores = declared_triangles_batch(tri_p, tri_q, trial[~contested], pairs[~contested], sigma)
    return build_batch(method="search", P=P, Q=Q, sigma=sigma, log_tau=np.full(len(P), np.nan), tri_p=tri_p,
                       tri_q=tri_q, tri_trial=tri_trial, triangle_pairs=tri_pairs, triangle_log_lr=scores,
                       declared=np.ones(len(tri_pairs), bool), pair_trial=trial, pairs=pairs,
                       n_conflicts=np.zeros(len(P), dtype=np.int64))
