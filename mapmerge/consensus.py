"""Consensus verification: which triangle matches agree on one rigid motion (beyond the paper).

True triangle matches all share one rigid motion (θ, t); chance congruences
between unrelated triangles do not. ``consensus_merge``:

1. takes the LP's tentative pairs that pass log τ (order-robust statistic;
   on the sparse large-map path every gated candidate that passes) as
   hypotheses, each with its own closed-form (θ_h, t_h); with more
   candidates than ``MAX_POOL``, a Hough vote in (θ, t) picks the pool;
2. counts, for every hypothesis, the candidate pairs whose three vertices it
   maps onto their partners within a χ²₆ gate. The gate's variance is the
   noise of both maps plus the hypothesis's own uncertainty at each vertex
   (translation and rotation error of a 3-point fit), so tolerances come
   from σ, not from hand-tuned constants;
3. keeps the largest transform-consistent set (at least
   ``MIN_CONSENSUS`` triangle pairs, otherwise "no match"; on large maps
   grown ring by ring from the hypothesis), refits with the n-point closed
   form dropping outliers, then associates *every* landmark one-to-one under
   the fitted transform (``mapmerge.association``), and
   refits on all associations (``ASSOCIATION_ROUNDS`` times), moves the
   transform to the maximum of the mixture likelihood of
   ``mapmerge.exhaustive`` (EM, which wrong pairs bias far less than a fit
   over hard pairs) and associates there once more, and accepts the match
   only if chance would rarely produce one as good (``match_nfa``, an a
   contrario test; the ``consensus_count`` variant, the library's default,
   ranks small maps' matches by their association count,
   ``count_nfa_batch``, at levels set per map size on unrelated tuning
   pairs);
4. declares every triangle pair whose three landmarks are associated and
   not contested (``association.declared_triangles_batch``), and fuses every
   association, so common landmarks appear once in the combined map.

When the triangles give no significant match, ``consensus_merge`` runs its
``fallback`` (the global search of ``mapmerge.search``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull
from scipy.special import chdtri, gammaln
from scipy.stats import binom

from .alignment import (
    align_pairs, fit_alignments, paired_transforms, prediction_var, prediction_vars, reject_outliers_batch,
    rotation, transform_covariances, wrap_angle,
)
from .association import (
    SHARED_PRIOR, associate_batch, covariance_rows, declared_triangles_batch, mapped_landmarks, own_covariances,
    pair_variances,
)
from .exhaustive import Mixture, Mixtures, bump_height, inside_hull, pair_noise
from .correspondence import correspondences, resolve_correspondences
from .matching import TriangleMatch
from .neighbours import njit
from .result import MergeBatch, build_batch
from .search import SEARCH_NFA, search_batch
from .triangles import MapHulls, centroids

#: Tail probability of every χ² gate (a true pair / landmark is rejected
#: with this probability).
GATE_P = 1e-3
#: Fewest transform-consistent triangle pairs accepted as a match: a single
#: chance congruence is common, two agreeing on one transform are not.
MIN_CONSENSUS = 2
#: Hypotheses tried (the best-scoring candidate pairs).
MAX_HYPOTHESES = 256
#: Candidates against which the hypotheses are first counted; with more
#: candidates than this, the pool is chosen by a Hough vote (``_hough_pool``).
MAX_POOL = 2048
#: Width of a θ bin of the Hough vote, in typical rotation uncertainties.
HOUGH_WIDTH = 3.0
#: Each round of ``_grow`` admits pairs this many times farther away.
GROW_FACTOR = 3.0
#: A match is accepted when its number of false alarms (``match_nfa``: the
#: expected number of equally good chance matches among the hypotheses
#: tried) is at most a level set by the smaller map's landmark count:
#: ``{most landmarks: level}``, the entry of the fewest landmarks that still
#: covers the map (``match_level``). The NFA bounds chance tightly on
#: 100-landmark maps and loosely on small ones, so a level chance reaches
#: at most about once in 1,000 unrelated pairs differs by size: the loosest
#: power of ten whose 95 % upper bound of the chance pass rate, on 10,000
#: unrelated tuning pairs per size, layout and SNR, stays below 1e-3
#: (docs/tuning.md). The search accepts at ``search.SEARCH_NFA``.
MATCH_NFA = {10: 1e-2, 20: 1e-3, np.inf: 1e-4}
#: ``count_nfa_batch``'s d² at which a landmark's chance partner is counted. Chosen among 0.25, 0.5, 1
#: and 2 by the triangle test's finds at one level per map size (at most 3 of 10,000 unrelated tuning
#: pairs, seeds 300000+, through in any cell) on the related pairs of seeds 100000+, 10 landmarks in both
#: layouts and 20 on the strip, 10-40 dB: 0.25 and 0.5 tie, 1 and 2 lose up to 7 points at 15 dB
#: (docs/small_maps.md).
COUNT_GATE = 0.5
#: The ``consensus_count`` variant's triangle test on maps whose smaller map holds at most
#: ``max(COUNT_LEVELS)`` landmarks: ``count_nfa_batch`` accepted at a log level per map size,
#: ``{most landmarks: log level}``, the entry of the fewest landmarks that still covers the map. Each is
#: the loosest level (rounded down to 0.01) at which at most ``TUNING_ALLOWED`` of 10,000 unrelated
#: tuning pairs (seeds 300000+) merge, the global search's merges (``SEARCH_COUNT_LEVELS``) counted first,
#: in every cell of its size (both layouts, 10-40 dB in 5 dB steps; ``experiments.small_maps --checks
#: count_levels``). Larger maps keep ``MATCH_NFA``, where the NFA is tight.
COUNT_LEVELS = {5: -5.45, 10: -15.57, 15: -22.67, 20: -28.69, 30: -57.51, 50: -65.11}
#: The ``consensus_count`` variant's global search on the same maps: its best hypothesis is accepted when
#: the search's own test passes (``search.SEARCH_NFA``) or when ``count_nfa_batch`` of its associations,
#: with one hypothesis, is at most a log level per map size (keys as ``COUNT_LEVELS``). On 10-landmark
#: maps the search's best hypothesis is the true transform for about half the related pairs at 20 dB,
#: which its own bound, sized for every (θ, t) it tried, almost never accepts. Each level is the loosest
#: (rounded down to 0.01) at which the search merges at most ``SEARCH_ALLOWED`` of 10,000 unrelated tuning
#: pairs (seeds 300000+) in every cell of its size; ``COUNT_LEVELS`` are then set with these merges
#: counted first (``experiments.small_maps --checks count_levels``). A cell whose own-test merges already
#: reach its allowance (30 landmarks, 10 dB: 2) may have none added by the count.
SEARCH_COUNT_LEVELS = {5: -6.15, 10: -16.35, 15: -24.48, 20: -32.2, 30: -47.29, 50: -66.96}
#: Unrelated tuning pairs of 10,000 that a size's two levels together let through in its worst cell, and
#: the search's share of them. A level binds in the cell whose tuning pairs happened to pass fewest, so
#: other cells of its size pass more on fresh pairs: at 3 the held-out check merged 4-6 of 10,000 in six
#: of its 84 cells (seeds 600000+), at 2 up to 11 (seeds 700000+); at 1 the check holds out seeds
#: 800000+. The search keeps its share: with ``SEARCH_ALLOWED`` = 0 instead, ``consensus_count`` found
#: fewer of 3,600 related tuning pairs (seeds 100000+) in 5 of 6 cells (docs/tuning.md).
TUNING_ALLOWED = 1
SEARCH_ALLOWED = 1
#: The χ² quantile of the triangle gate: 3 vertices (6 coordinates).
GATE_6 = float(chdtri(6, GATE_P))
#: Hypotheses (most inliers first) refitted on their inliers and recounted.
REFINE = 32
#: Refit-and-associate rounds after the consensus fit, before the EM step: one, as the
#: EM step after it leaves a second nothing to improve (docs/tuning.md).
ASSOCIATION_ROUNDS = 1


@njit(cache=True)
def _misfit2(p, q, c, s, tx, ty):
    """‖q - (R(θ) p + t)‖² of one vertex pair (rows p, q), R(θ) given by c = cos θ, s = sin θ."""
    ex = q[0] - (c * p[0] - s * p[1] + tx)
    ey = q[1] - (s * p[0] + c * p[1] + ty)
    return ex * ex + ey * ey


@njit(cache=True)
def _gate_d2_kernel(cp, cq, first, size, cos, sin, t, var):
    """χ²₆-distributed misfits of triangle pairs under H transforms (cos θ, sin θ: (H,), from numpy, whose
    trigonometry sets the bits): transform h against pairs ``first[h]:first[h] + size[h]`` of cp, cq
    ((m, 3, 2)); var (Σ size, 3). Returns (Σ size,), transform by transform."""
    d2 = np.empty(size.sum())
    m = 0
    for h in range(len(cos)):
        for k in range(first[h], first[h] + size[h]):
            acc = 0.0
            for v in range(3):
                acc += _misfit2(cp[k, v], cq[k, v], cos[h], sin[h], t[h, 0], t[h, 1]) / var[m, v]
            d2[m] = acc
            m += 1
    return d2


def _gate_d2(cp, cq, theta, t, var):
    """χ²₆-distributed misfit of m paired triangles (cp, cq: (m, 3, 2)) under one transform (θ scalar,
    t (2,), var (m, 3)) or under H (θ (H,), t (H, 2), var (H, m, 3)): (m,) or (H, m)."""
    theta = np.asarray(theta, dtype=float)
    H, m = theta.size, len(cp)
    d2 = _gate_d2_kernel(cp, cq, np.zeros(H, dtype=np.int64), np.full(H, m, dtype=np.int64),
                         np.cos(theta.reshape(-1)), np.sin(theta.reshape(-1)), np.reshape(t, (-1, 2)),
                         np.reshape(var, (-1, 3)))
    return d2.reshape(theta.shape + cp.shape[:1])


@njit(cache=True)
def _hypothesis_inliers(cp, cq, first, size, cos, sin, t, centre, spread, two_var, gate):
    """Which candidate pairs each 3-point hypothesis (cos θ, sin θ, t, its p triangle's centroid and
    Σ‖p̃‖²) gates in: hypothesis h against pairs ``first[h]:first[h] + size[h]`` of cp, cq ((m, 3, 2)).
    Returns (Σ size,) bool, hypothesis by hypothesis.

    Per coordinate the variance is both maps' noise, t's at the centroid (2σ²/3) and the rotation error
    2σ²/Σ‖p̃‖² times the squared lever arm; ``two_var`` (H,) is 2σ².
    """
    inliers = np.empty(size.sum(), dtype=np.bool_)
    m = 0
    for h in range(len(cos)):
        for k in range(first[h], first[h] + size[h]):
            acc = 0.0
            for v in range(3):
                dx, dy = cp[k, v, 0] - centre[h, 0], cp[k, v, 1] - centre[h, 1]
                var = two_var[h] * (1 + 1 / 3 + (dx * dx + dy * dy) / spread[h])
                acc += _misfit2(cp[k, v], cq[k, v], cos[h], sin[h], t[h, 0], t[h, 1]) / var
            inliers[m] = acc <= gate
            m += 1
    return inliers


@dataclass(frozen=True)
class _Pool:
    """Candidate triangle pairs of one or more map pairs and the pools their hypotheses are counted on.

    ``pool`` lists the candidates (positions into vp, vq), each map pair's
    best first; map pair b's are ``pool[first[b]:first[b] + size[b]]``, and
    cp, cq hold their triangles' coordinates in pool order.
    """

    vp: np.ndarray  # (C, 3) vertices of the candidates' p triangles, paired with vq's
    vq: np.ndarray
    P: np.ndarray  # (B, n_p, 2)
    Q: np.ndarray
    scores: np.ndarray  # (C,) log Λ
    sigma: np.ndarray  # (B,)
    pool: np.ndarray
    first: np.ndarray
    size: np.ndarray
    cp: np.ndarray
    cq: np.ndarray

    @classmethod
    def of(cls, vp, vq, P, Q, scores, sigma, trial, pool=None) -> "_Pool":
        """The pools of candidates grouped by map pair (``trial``, ascending), by default every candidate,
        best first."""
        B, n_p, n_q = len(P), P.shape[1], Q.shape[1]
        pool = np.lexsort((-scores, trial)) if pool is None else pool
        first = np.searchsorted(trial[pool], np.arange(B + 1))
        # np.take, not fancy indexing: several times faster than P[vp] at 10^7 rows.
        cp = np.take(P.reshape(-1, 2), vp[pool] + (trial[pool] * n_p)[:, None], axis=0)
        cq = np.take(Q.reshape(-1, 2), vq[pool] + (trial[pool] * n_q)[:, None], axis=0)
        return cls(vp, vq, P, Q, scores, sigma, pool, first[:-1], np.diff(first), cp, cq)

    def two_var(self, pair) -> np.ndarray:
        """2σ² of map pairs ``pair`` (``association.pair_variances``: the bits of the gates)."""
        return pair_variances(self.sigma)[pair]


def _rows_of_blocks(size):
    """Rows of blocks of ``size`` rows laid end to end: each row's block and its place within the block."""
    block = np.repeat(np.arange(len(size)), size)
    return block, np.arange(block.size) - np.repeat(np.cumsum(size) - size, size)


def _hypotheses(cand: _Pool):
    """Each map pair's ``MAX_HYPOTHESES`` best candidates as 3-point hypotheses, and their inliers.

    Returns the hypotheses' pool rows, their map pairs and their inliers:
    hypothesis h's among its map pair's pool are the flags
    ``inliers[block[h]:block[h] + size[pair[h]]]``.
    """
    pair, rank = _rows_of_blocks(cand.size)
    hyp = np.flatnonzero(rank < MAX_HYPOTHESES)
    pair = pair[hyp]
    theta, t, _ = paired_transforms(cand.cp[hyp], cand.cq[hyp])
    centre = centroids(cand.cp[hyp])
    spread = np.sum((cand.cp[hyp] - centre[:, None]) ** 2, axis=(1, 2))  # Σ‖p̃‖²
    inliers = _hypothesis_inliers(cand.cp, cand.cq, cand.first[pair], cand.size[pair], np.cos(theta),
                                  np.sin(theta), t, centre, spread, cand.two_var(pair), GATE_6)
    block = np.cumsum(cand.size[pair]) - cand.size[pair]
    return hyp, pair, inliers, block


def _consensus_groups(vp, vq, P, Q, scores, sigma, trial):
    """Each map pair's largest transform-consistent group of candidate pairs, every map pair at once.

    Every candidate's own 3-point transform is a hypothesis; its inliers
    among its map pair's candidates are gated with the hypothesis's
    uncertainty (loose for small triangles). The ``REFINE`` best hypotheses
    of each map pair are then refitted on their inliers' landmarks and
    recounted with the refit's much smaller uncertainty, which is what
    separates the true group from loose chance groups. A map pair's group
    is its largest refitted one, of highest total log Λ among equals, the
    first among those.

    Parameters
    ----------
    vp, vq : (C, 3) int ndarray
        Candidate triangle pairs' vertices.
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    scores : (C,) ndarray
    sigma : (B,) ndarray
    trial : (C,) int ndarray
        Map pair of each candidate, ascending; at most ``MAX_POOL`` a map pair.

    Returns
    -------
    (C,) bool ndarray
        The candidates of each map pair's group.
    """
    cand = _Pool.of(vp, vq, P, Q, scores, sigma, trial)
    hyp, pair, inliers, block = _hypotheses(cand)
    count = np.add.reduceat(inliers, block) if len(hyp) else np.empty(0, dtype=np.intp)
    # Per map pair, most inliers first, then the best score; the first REFINE with at least MIN_CONSENSUS.
    order = np.lexsort((-scores[cand.pool[hyp]], -count, pair))
    in_pair = np.arange(len(order)) - np.searchsorted(pair[order], pair[order])
    order = order[(in_pair < REFINE) & (count[order] >= MIN_CONSENSUS)]
    # Each refitted hypothesis's inliers: (hypothesis, pool row).
    h, at = _rows_of_blocks(cand.size[pair[order]])
    inside = inliers[block[order][h] + at]
    chosen = np.zeros(len(vp), dtype=bool)
    chosen[_refit_groups(cand, pair[order], h[inside], cand.first[pair[order]][h[inside]] + at[inside])] = True
    return chosen


def _refit_groups(cand: _Pool, pair, h, row):
    """Each map pair's best group after one refit of its hypotheses on their inliers' landmarks.

    Hypothesis k (of map pair ``pair[k]``) has the inliers at pool rows
    ``row[h == k]``. Their landmark correspondences are resolved per
    hypothesis (landmark indices offset per hypothesis, so none competes
    with another's) and fitted, and the hypothesis's map pair's pool is gated
    under each fit; hypotheses with fewer than 3 correspondences are left
    out. Returns the positions (into vp, vq) of each map pair's chosen group:
    its largest, of highest total log Λ among equals, the first among those.
    """
    P, Q, pool, n_p, n_q = cand.P, cand.Q, cand.pool, cand.P.shape[1], cand.Q.shape[1]
    members = pool[row]
    uniq, keep, _ = resolve_correspondences(cand.vp[members] + n_p * h[:, None], cand.vq[members] + n_q * h[:, None],
                                            cand.scores[members])
    (kp, kq), owner = uniq[keep].T, uniq[keep, 0] // n_p  # owner: the hypothesis of each correspondence
    xp = P.reshape(-1, 2)[pair[owner] * n_p + kp % n_p]
    xq = Q.reshape(-1, 2)[pair[owner] * n_q + kq % n_q]
    fitted = np.flatnonzero(np.bincount(owner, minlength=len(pair)) >= 3)
    if fitted.size == 0:
        return np.empty(0, dtype=np.intp)
    # Every fit's (θ, t) covariance and prediction variance at once (``Alignment.cov``, ``prediction_var``).
    theta, t, _, cov = fit_alignments(owner, xp, xq, cand.sigma[pair], len(pair))
    fpair = pair[fitted]
    size = cand.size[fpair]
    fit, at = _rows_of_blocks(size)
    rows = cand.first[fpair][fit] + at
    var = cand.two_var(fpair)[fit, None] + prediction_vars(cand.cp[rows], theta[fitted][fit], cov[fitted][fit])
    inside = _gate_d2_kernel(cand.cp, cand.cq, cand.first[fpair], size, np.cos(theta[fitted]),
                             np.sin(theta[fitted]), t[fitted], var) <= GATE_6
    n_in = np.bincount(fit[inside], minlength=fitted.size)
    largest = np.zeros(len(cand.size), dtype=np.intp)
    np.maximum.at(largest, fpair, n_in)
    tied = np.flatnonzero((n_in == largest[fpair]) & (n_in > 0))
    n_tied = np.bincount(fpair[tied], minlength=len(cand.size))
    win = np.zeros(fitted.size, dtype=bool)
    win[tied[n_tied[fpair[tied]] == 1]] = True
    # Equally large groups: the highest total log Λ, the first among equals (summed as numpy sums one group).
    start = np.cumsum(size) - size
    contest = {}
    for f in tied[n_tied[fpair[tied]] > 1]:
        sl = slice(start[f], start[f] + size[f])
        total = float(cand.scores[pool[rows[sl][inside[sl]]]].sum())
        if fpair[f] not in contest or total > contest[fpair[f]][0]:
            contest[fpair[f]] = (total, f)
    win[[f for _, f in contest.values()]] = True
    return pool[rows[win[fit] & inside]]


def _grown_group(vp, vq, P, Q, scores, sigma):
    """One large map pair's largest transform-consistent group of candidate pairs (more than ``MAX_POOL``).

    The hypotheses are counted on the candidates of a Hough vote's densest
    transform (``_hough_pool``): large maps have far more candidates than
    any transform needs, and the landmark association that follows brings
    every landmark back in. Each of the ``REFINE`` best hypotheses grows
    its group ring by ring (``_grow``); the largest group wins, of highest
    total log Λ among equals.
    """
    cp, cq = np.take(P, vp, axis=0), np.take(Q, vq, axis=0)
    pool = _hough_pool(cp, cq, scores, sigma)
    cand = _Pool.of(vp, vq, P[None], Q[None], scores, np.array([sigma]), np.zeros(len(vp), dtype=np.intp), pool)
    hyp, _, inliers, block = _hypotheses(cand)
    count = np.add.reduceat(inliers, block)
    order = np.lexsort((-scores[pool[hyp]], -count))[:REFINE]
    order = order[count[order] >= MIN_CONSENSUS]
    centres = centroids(cand.cp)
    best, best_key = np.empty(0, dtype=np.intp), (0, 0.0)
    for h in order:
        members = _grow(cand, centres, pool[hyp[h]], GATE_6)
        key = (members.size, float(scores[members].sum()))
        if key > best_key:
            best, best_key = members, key
    return best


def _grow(cand: _Pool, centres, seed, gate):
    """Grow a transform-consistent group outwards from one hypothesis (candidate ``seed``).

    A single triangle's rotation is too uncertain to judge far-away pairs
    (its gate must be loose there, and loose gates let chance pairs in), so
    pairs are admitted ring by ring, ``GROW_FACTOR`` times farther each
    round, each ring gated under the refit of everything admitted so far.
    ``cand``: the pool of one map pair; ``centres``: the centroid of each pool member's p triangle.
    """
    vp, vq, scores, pool = cand.vp, cand.vq, cand.scores, cand.pool
    P, Q, sigma = cand.P[0], cand.Q[0], float(cand.sigma[0])
    dist = np.linalg.norm(centres - P[vp[seed]].mean(axis=0), axis=1)
    side = np.sqrt(np.sum((P[vp[seed]] - P[vp[seed]].mean(axis=0)) ** 2) / 2)
    al = align_pairs(P[vp[seed]], Q[vq[seed]], sigma)
    radius, members = GROW_FACTOR * side, np.array([seed])
    while True:
        var = 2 * sigma**2 + prediction_var(cand.cp, al)
        within = dist <= radius
        members = pool[within & (_gate_d2(cand.cp, cand.cq, al.theta, al.t, var) <= gate)]
        pairs, _ = correspondences(vp[members], vq[members], scores[members])
        if pairs.shape[0] >= 3:
            al = align_pairs(P[pairs[:, 0]], Q[pairs[:, 1]], sigma)
        if within.all():
            return members
        radius *= GROW_FACTOR


def _hough_pool(cp, cq, scores, sigma):
    """The candidates around the densest transform: a Hough vote in (θ, t).

    With many more candidates than a transform needs (large maps), most are
    chance congruences whose (θ, t) scatter over all rotations and the whole
    map, while true pairs pile up at one (θ, t). θ is voted in bins a few
    times the rotation uncertainty of a typical triangle wide, then t,
    evaluated at the winning θ, in cells as wide as that θ window spreads a
    true pair's t. Returns up to ``MAX_POOL`` candidates of the winning
    cell and its neighbours, best scores first.
    """
    theta, _, _ = paired_transforms(cp, cq)
    p_bar, q_bar = centroids(cp), centroids(cq)
    spread = np.median(np.sum((cp - p_bar[:, None]) ** 2, axis=(1, 2)))
    side = np.sqrt(spread / 2)  # about a typical side length
    sigma_theta = np.sqrt(2 * sigma**2 / spread)  # rotation error of a typical triangle fit
    n_bins = int(np.clip(2 * np.pi / (HOUGH_WIDTH * sigma_theta), 8, 4096))
    counts, edges = np.histogram(theta, bins=n_bins, range=(-np.pi, np.pi))
    window = (counts + np.roll(counts, 1) + np.roll(counts, -1)).argmax()  # circular, 3 bins
    theta_hat, half = 0.5 * (edges[window] + edges[window + 1]), 1.5 * (edges[1] - edges[0])
    idx = np.flatnonzero(np.abs(wrap_angle(theta - theta_hat)) <= half)
    # t is evaluated at θ̂ about the map centre: a true pair's θ may be off
    # θ̂ by up to the half window, which moves its t by that angle times its
    # distance from the centre, so the t cells are that wide.
    centre = cp.reshape(-1, 2).mean(axis=0)
    reach = np.sqrt(np.mean(np.sum((p_bar[idx] - centre) ** 2, axis=1)))
    t = q_bar[idx] - (p_bar[idx] - centre) @ rotation(theta_hat).T
    cell = np.floor(t / max(side, half * reach)).astype(np.int64)
    keys, inverse, votes = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
    # The winning t cell and its 8 neighbours.
    best = keys[np.argmax(votes)]
    idx = idx[np.all(np.abs(cell - best) <= 1, axis=1)]
    return idx[np.argsort(-scores[idx], kind="stable")][:MAX_POOL]

def match_level(n_landmarks: int) -> float:
    """The NFA at most which consensus accepts a triangle match between maps whose smaller holds
    ``n_landmarks`` landmarks (``MATCH_NFA``)."""
    return MATCH_NFA[min(most for most in MATCH_NFA if most >= n_landmarks)]


def _size_entry(levels: dict, n_landmarks: int) -> float:
    """The entry of ``levels`` ({most landmarks: level}) of the fewest landmarks that still covers the map."""
    return levels[min(m for m in levels if m >= n_landmarks)]


def triangle_test(n_landmarks: int, statistic: str = "nfa"):
    """The triangle test between maps whose smaller holds ``n_landmarks`` landmarks: (its batch statistic, the
    level at most which it accepts). ``"nfa"``: ``match_nfa_batch`` at ``match_level``; ``"count"``:
    ``count_nfa_batch`` at ``COUNT_LEVELS`` on maps of up to ``max(COUNT_LEVELS)`` landmarks, the ``"nfa"``
    test on larger ones."""
    if statistic == "count" and n_landmarks <= max(COUNT_LEVELS):
        return count_nfa_batch, float(np.exp(_size_entry(COUNT_LEVELS, n_landmarks)))
    return match_nfa_batch, match_level(n_landmarks)


def search_count_level(n_landmarks: int) -> float | None:
    """``SEARCH_COUNT_LEVELS``' log level for maps whose smaller holds ``n_landmarks`` landmarks; None above
    ``max(SEARCH_COUNT_LEVELS)``, where the search keeps its own test alone (as it does at a level of -inf)."""
    return _size_entry(SEARCH_COUNT_LEVELS, n_landmarks) if n_landmarks <= max(SEARCH_COUNT_LEVELS) else None


def search_count_nfa(P, Q, sigma, cov_p=None, cov_q=None, hulls=None, fallback=search_batch):
    """The global search's best hypothesis of B map pairs associated whatever its NFA, and its two statistics.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    sigma : (B,) ndarray
    cov_p, cov_q : (B, n, 2, 2) ndarray, optional
    hulls : (MapHulls, MapHulls), optional
    fallback : callable
        ``search.search_batch`` or a ``search.SearchMemo``.

    Returns
    -------
    trial, pairs, contested : (K,), (K, 2), (K,) ndarray
        ``search_batch``'s associations at ``nfa_level=np.inf``.
    nfa : (B,) ndarray
        The search's own NFA of each pair's best hypothesis.
    log_count_nfa : (B,) ndarray
        The log of ``count_nfa_batch`` of its associations with one hypothesis, at their n-point fit (inf
        where fewer than 3 landmarks associate; -inf where the NFA underflows).
    """
    hulls = (MapHulls(P), MapHulls(Q)) if hulls is None else hulls
    trial, pairs, contested, nfa = fallback(P, Q, sigma, cov_p, cov_q, hulls, nfa_level=np.inf)
    log_count_nfa = np.full(len(P), np.inf)
    active, local, kept, theta, t, _, cov = _fitted(P, Q, sigma, trial, pairs)
    if active.size:
        count_nfa = count_nfa_batch(P[active], Q[active], theta, t, cov, local, kept, np.ones(active.size),
                                    sigma[active], covariance_rows(cov_p, active), covariance_rows(cov_q, active),
                                    [hulls[0][b] for b in active])
        with np.errstate(divide="ignore"):
            log_count_nfa[active] = np.log(count_nfa)
    return trial, pairs, contested, nfa, log_count_nfa


def match_nfa(P, Q, alignment, pairs, n_hypotheses: int, sigma: float, *, cov_p=None, cov_q=None,
              hull=None) -> float:
    """Number of false alarms of a match, a contrario (Moisan & Stival 2004).

    Under "unrelated maps", a q landmark mapped inside map p's hull finds a p
    landmark within Mahalanobis radius d² by chance with probability
    ``α(d²) = ρ_p · π · √det C · d²`` (ρ_p the landmark density of p, C the
    gate covariance). For the k tightest associations, the 3 that fix a
    hypothesis excepted, chance gives them with probability at most
    ``C(N, k - 3) α(d²_(k))^(k-3)`` among the N landmarks inside the hull;
    with ``n_hypotheses`` hypotheses tried, NFA is the smallest
    ``n_hypotheses · C(N, k - 3) · α(d²_(k))^(k-3)`` over k. A match with
    NFA <= ε is expected to arise by chance at most ε times per map pair
    (consensus accepts at ε = ``match_level`` of the maps' size).
    ``hull``: P's convex hull, when the caller has it. One map pair's
    ``match_nfa_batch``.
    """
    one = (lambda a: None if a is None else np.asarray(a)[None])
    return float(match_nfa_batch(P[None], Q[None], np.array([alignment.theta], dtype=float), one(alignment.t),
                                 one(alignment.cov), np.zeros(len(pairs), dtype=np.intp), pairs,
                                 np.array([n_hypotheses]), np.array([sigma], dtype=float), one(cov_p), one(cov_q),
                                 None if hull is None else [hull])[0])


def _chance_terms(P, Q, theta, t, cov, trial, pairs, sigma, cov_p, cov_q, hulls):
    """What both acceptance statistics need of B map pairs: each one's chance area per unit d²
    (ρ_p · π · √det C, averaged over its mapped q landmarks), the landmarks mapped inside p's hull (its
    associated ones counted however far out), and each association's Mahalanobis d² (K,)."""
    B = len(P)
    cov_p = own_covariances(cov_p, P.shape[1], sigma)
    x, cov_x = mapped_landmarks(Q, theta, t, cov, sigma, cov_q)
    typical = np.median(np.trace(cov_p, axis1=-2, axis2=-1) / 2, axis=1)  # a typical p landmark
    hulls = [ConvexHull(P[b]) for b in range(B)] if hulls is None else hulls
    inside = np.stack([inside_hull(hull, x[b]) for b, hull in enumerate(hulls)])
    density = P.shape[1] / np.array([hull.volume for hull in hulls])  # a 2-D hull's "volume" is its area
    counted = inside.copy()
    counted[trial, pairs[:, 1]] = True
    root_det = np.sqrt(np.linalg.det(cov_x + typical[:, None, None, None] * np.eye(2)))
    unit_area = density * np.pi * np.sum(root_det, axis=1, where=counted) / counted.sum(axis=1)
    e = P[trial, pairs[:, 0]] - x[trial, pairs[:, 1]]
    cov_pairs = cov_x[trial, pairs[:, 1]] + cov_p[trial, pairs[:, 0]]
    d2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov_pairs), e)
    return unit_area, inside.sum(axis=1), d2


def match_nfa_batch(P, Q, theta, t, cov, trial, pairs, n_hypotheses, sigma, cov_p=None, cov_q=None,
                    hulls=None) -> np.ndarray:
    """``match_nfa`` of B map pairs at once, each with its own transform and associations.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    theta, t, cov : (B,), (B, 2), (B, 3, 3) ndarray
        Each map pair's fitted transform and its (θ, t) covariance.
    trial, pairs : (K,), (K, 2) int ndarray
        The associations (p index, q index) and their map pair; at least 3 per map pair.
    n_hypotheses, sigma : (B,) ndarray
    cov_p, cov_q : (B, n, 2, 2) ndarray, optional
    hulls : list of ConvexHull, optional
        Each P's convex hull.

    Returns
    -------
    (B,) ndarray
        NFA of each map pair's match.
    """
    B = len(P)
    unit_area, n_inside, d2 = _chance_terms(P, Q, theta, t, cov, trial, pairs, sigma, cov_p, cov_q, hulls)
    order = np.lexsort((d2, trial))
    trial, d2 = trial[order], d2[order]
    count = np.bincount(trial, minlength=B)
    k = np.arange(len(trial)) - (np.cumsum(count) - count)[trial] + 1  # rank within the map pair
    use = k >= 4
    trial, free, d2 = trial[use], k[use] - 3, d2[use]
    n_in = np.maximum(n_inside, count)[trial]
    alpha = np.minimum(1.0, unit_area[trial] * d2)
    log_comb = gammaln(n_in + 1) - gammaln(free + 1) - gammaln(n_in - free + 1)
    log_nfa = np.full(B, np.inf)
    np.minimum.at(log_nfa, trial, np.log(n_hypotheses[trial]) + log_comb + free * np.log(np.maximum(alpha, 1e-300)))
    return np.where(np.isfinite(log_nfa), np.exp(log_nfa), np.asarray(n_hypotheses, dtype=float))


def count_nfa_batch(P, Q, theta, t, cov, trial, pairs, n_hypotheses, sigma, cov_p=None, cov_q=None,
                    hulls=None) -> np.ndarray:
    """The number of false alarms of B matches counted by their associations alone (``consensus_count``'s test).

    Each association is made by the association's own posterior gate, which
    tightens as the maps crowd, so the count of associations carries the
    evidence; how close each pair lies adds little on small maps. With k
    associations, N landmarks mapped inside p's hull and a chance partner
    for a landmark at probability ``α = ρ_p π √det C · COUNT_GATE`` (the
    chance area of ``match_nfa`` at d² = ``COUNT_GATE``), the NFA is
    ``n_hypotheses · P(Bin(N - 3, α) >= k - 3)``: the three associations
    that fix a hypothesis excepted. Same arguments and returns as
    ``match_nfa_batch``; a map pair with fewer than 4 associations gets
    its hypothesis count.

    It is not a bound: ``COUNT_GATE`` is far smaller than the association's
    own gate, so chance is understated by orders of magnitude (on unrelated
    tuning pairs 3 in 10,000 reach about e^-13 at 10 landmarks and e^-26 at
    20). Only its order is used, against a level calibrated per map size
    (``COUNT_LEVELS``).
    """
    unit_area, n_inside, _ = _chance_terms(P, Q, theta, t, cov, trial, pairs, sigma, cov_p, cov_q, hulls)
    k = np.bincount(trial, minlength=len(P))
    free = np.maximum(n_inside, k) - 3
    alpha = np.minimum(1.0, unit_area * COUNT_GATE)
    log_nfa = np.log(np.asarray(n_hypotheses, dtype=float)) + binom.logsf(k - 4, free, alpha)
    return np.where(k >= 4, np.exp(log_nfa), np.asarray(n_hypotheses, dtype=float))


def _triangle_correspondences(P, Q, sigma, match: TriangleMatch, log_tau):
    """Each map pair's landmark correspondences from its largest transform-consistent group of
    candidate triangle pairs, outliers rejected.

    The candidates are the tentative pairs passing log τ; map pairs with
    more than ``MAX_POOL`` of them (large maps) are grouped one at a time
    (``_grown_group``), the others all at once (``_consensus_groups``).
    Returns (trial, pairs) of the correspondences, the conflicts of each map
    pair and its number of candidates (the hypotheses tried).
    """
    B = len(P)
    passing = np.flatnonzero(match.log_lr >= log_tau[match.trial])
    n_candidates = np.bincount(match.trial[passing], minlength=B)
    passing = passing[n_candidates[match.trial[passing]] >= MIN_CONSENSUS]
    trial, vp, vq = match.trial[passing], match.p_vertices[passing], match.q_vertices[passing]
    scores = match.log_lr[passing]
    large = n_candidates[trial] > MAX_POOL
    chosen = np.zeros(len(passing), dtype=bool)
    chosen[~large] = _consensus_groups(vp[~large], vq[~large], P, Q, scores[~large], sigma, trial[~large])
    for b in np.unique(trial[large]):
        cand = np.flatnonzero(trial == b)
        chosen[cand[_grown_group(vp[cand], vq[cand], P[b], Q[b], scores[cand], float(sigma[b]))]] = True
    chosen &= np.bincount(trial[chosen], minlength=B)[trial] >= MIN_CONSENSUS
    # Landmark indices offset by map pair, so that one call resolves every pair's conflicts.
    n = max(P.shape[1], Q.shape[1])
    offset = trial[chosen][:, None] * n
    uniq, keep, _ = resolve_correspondences(offset + vp[chosen], offset + vq[chosen], scores[chosen])
    trial, pairs = uniq[keep, 0] // n, (uniq[keep] % n).astype(np.intp)
    inlying = reject_outliers_batch(P, Q, trial, pairs, sigma, GATE_P)
    return trial[inlying], pairs[inlying], np.bincount(uniq[~keep, 0] // n, minlength=B), n_candidates


def _fitted(P, Q, sigma, trial, pairs):
    """The map pairs with at least 3 associations, their associations renumbered to them and the n-point
    fit of each: (active, local trial, pairs, θ, t, µ, (θ, t) covariance)."""
    count = np.bincount(trial, minlength=len(P))
    active = np.flatnonzero(count >= 3)
    use = count[trial] >= 3
    local, pairs = (np.cumsum(count >= 3) - 1)[trial[use]], pairs[use]
    theta, t, mu, cov = fit_alignments(local, P[trial[use], pairs[:, 0]], Q[trial[use], pairs[:, 1]],
                                       sigma[active], len(active))
    return active, local, pairs, theta, t, mu, cov


def _associate_fitted(P, Q, sigma, trial, pairs, cov_p, cov_q, hulls, *, mixture: bool, with_margin: bool):
    """Associate every landmark of each map pair with at least 3 associations under their fit.

    With ``mixture``, the transform first moves to the maximum of the mixture
    likelihood of ``mapmerge.exhaustive`` (EM). Below about 15 dB a tenth of
    the associations can be wrong, and the fit over them is biased by
    degrees, which in turn pairs landmarks wrongly; EM weighs each possible
    partner by its posterior instead of trusting one hard pairing.
    """
    active, local, pairs, theta, t, mu, cov = _fitted(P, Q, sigma, trial, pairs)
    if active.size == 0:
        return active, pairs, np.empty(0, dtype=bool)
    if mixture:
        s = [pair_noise(float(sigma[b]), covariance_rows(cov_p, b), covariance_rows(cov_q, b)) for b in active]
        c = [bump_height(P.shape[1], hulls[b][0].volume, s_b, SHARED_PRIOR) for b, s_b in zip(active, s)]
        models = Mixture.of_maps(P[active], s, c, SHARED_PRIOR, [hulls[b][0] for b in active])
        theta, t = Mixtures.of(models).em(Q[active], np.arange(active.size), theta, t)
        cov = transform_covariances(local, mu, theta, sigma[active], np.ones(len(active), dtype=bool))
    tr, pairs, contested = associate_batch(P[active], Q[active], theta, t, cov, sigma[active],
                                           covariance_rows(cov_p, active), covariance_rows(cov_q, active),
                                           [hulls[b] for b in active], with_margin)
    return active[tr], pairs, contested


def _verified_pairs(P, Q, sigma, trial, pairs, n_hypotheses, cov_p, cov_q, hulls_p, hulls_q, statistic):
    """Each map pair's associations from its triangle correspondences, kept only where significant.

    Associate under the correspondences' fit (``ASSOCIATION_ROUNDS`` times),
    then at the mixture's maximum-likelihood transform, and accept a map
    pair's associations only if they pass the ``triangle_test`` of its maps' size and ``statistic``.
    Returns (trial, pairs, contested) of the accepted associations.
    """
    hulls = {b: (hulls_p[b], hulls_q[b]) for b in np.flatnonzero(np.bincount(trial, minlength=len(P)) >= 3)}
    # These rounds' contested pairs are never returned: the mixture step associates again.
    for _ in range(ASSOCIATION_ROUNDS):
        trial, pairs, _ = _associate_fitted(P, Q, sigma, trial, pairs, cov_p, cov_q, hulls, mixture=False,
                                            with_margin=False)
    trial, pairs, contested = _associate_fitted(P, Q, sigma, trial, pairs, cov_p, cov_q, hulls, mixture=True,
                                                with_margin=True)
    active, local, kept, theta, t, _, cov = _fitted(P, Q, sigma, trial, pairs)
    contested = contested[np.bincount(trial, minlength=len(P))[trial] >= 3]
    if active.size == 0:
        return trial[:0], kept, contested
    test, level = triangle_test(min(P.shape[1], Q.shape[1]), statistic)
    nfa = test(P[active], Q[active], theta, t, cov, local, kept, n_hypotheses[active], sigma[active],
               covariance_rows(cov_p, active), covariance_rows(cov_q, active), [hulls[b][0] for b in active])
    accepted = (nfa <= level)[local]
    return active[local][accepted], kept[accepted], contested[accepted]


def consensus_merge(P, Q, sigma, match: TriangleMatch, log_tau, cov_p=None, cov_q=None,
                    fallback=None, statistic: str = "nfa") -> MergeBatch:
    """The ``method="consensus"`` (``statistic="count"``: ``"consensus_count"``) merge of a batch of map pairs.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    sigma, log_tau : (B,) ndarray
    match : TriangleMatch
        Tentative pairs with the order-robust statistic.
    cov_p, cov_q : (B, n, 2, 2) ndarray, optional
        Per-landmark covariances.
    fallback : callable, optional
        ``fallback(P, Q, sigma, cov_p, cov_q, hulls) -> (trial, pairs, contested, nfa)``
        for the map pairs whose triangles give no significant match, all at
        once (``search.search_batch``: the global search; ``hulls``: their
        maps' ``MapHulls``).
    statistic : {"nfa", "count"}
        The triangle test's statistic (``triangle_test``).

    Returns
    -------
    MergeBatch
        ``triangle_pairs`` holds, per map pair, the declared pairs (three
        uncontested landmarks associated) followed by the remaining
        tentative pairs, undeclared, so that their labels still count as
        misses or true negatives.
    """
    trial, pairs, n_conflicts, n_candidates = _triangle_correspondences(P, Q, sigma, match, log_tau)
    hulls_p, hulls_q = match.tri_p.hulls, match.tri_q.hulls
    trial, pairs, contested = _verified_pairs(P, Q, sigma, trial, pairs, n_candidates, cov_p, cov_q, hulls_p, hulls_q,
                                              statistic)
    if fallback is not None:
        unmatched = np.flatnonzero(np.bincount(trial, minlength=len(P)) == 0)
        level = search_count_level(min(P.shape[1], Q.shape[1])) if statistic == "count" else None
        if unmatched.size:
            args = (P[unmatched], Q[unmatched], sigma[unmatched], covariance_rows(cov_p, unmatched),
                    covariance_rows(cov_q, unmatched), (hulls_p.take(unmatched), hulls_q.take(unmatched)))
            if level is None or level == -np.inf:  # the search's own test alone: no count to take
                found, more, more_contested, _ = fallback(*args)
            else:
                found, more, more_contested, nfa, log_count_nfa = search_count_nfa(*args, fallback=fallback)
                accepted = ((nfa <= SEARCH_NFA) | (log_count_nfa <= level))[found]
                found, more, more_contested = found[accepted], more[accepted], more_contested[accepted]
            trial = np.concatenate([trial, unmatched[found]])
            order = np.argsort(trial, kind="stable")
            trial = trial[order]
            pairs = np.concatenate([pairs, more])[order]
            contested = np.concatenate([contested, more_contested])[order]
    tri_p, tri_q = match.tri_p, match.tri_q
    tri_trial, tri_pairs, tri_scores = declared_triangles_batch(tri_p, tri_q, trial[~contested], pairs[~contested],
                                                                sigma)
    # The LP's other tentative pairs follow undeclared, so that their labels still count as misses or true negatives.
    def key(tr, tp):
        return (tri_p.offsets[tr] + tp[:, 0]) * tri_q.offsets[-1] + tri_q.offsets[tr] + tp[:, 1]

    rest = ~np.isin(key(match.trial, match.triangle_pairs), key(tri_trial, tri_pairs))
    order = np.argsort(np.concatenate([tri_trial, match.trial[rest]]), kind="stable")
    method = "consensus" if statistic == "nfa" else "consensus_count"
    return build_batch(method=method, P=P, Q=Q, sigma=sigma, log_tau=log_tau, tri_p=tri_p, tri_q=tri_q,
                       tri_trial=np.concatenate([tri_trial, match.trial[rest]])[order],
                       triangle_pairs=np.concatenate([tri_pairs, match.triangle_pairs[rest]]).astype(np.intp)[order],
                       triangle_log_lr=np.concatenate([tri_scores, match.log_lr[rest]])[order],
                       declared=np.r_[np.ones(len(tri_pairs), bool), np.zeros(int(rest.sum()), bool)][order],
                       pair_trial=trial, pairs=pairs, n_conflicts=n_conflicts)
