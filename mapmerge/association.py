"""Landmark association under a fitted transform (beyond the paper).

Once a rigid motion (θ, t) relates two maps, which landmark of q is which
of p? ``associate`` answers one-to-one, by posterior log-odds against
"unshared": ``posterior_association`` scores every pair by its full
covariance (both maps' noise and the transform's error) and q's landmark
density, and solves one assignment per connected component of the
positively scored pairs, with each pair's margin to its best alternative
(``AMBIGUITY`` marks the contested ones). The prior that a landmark is
shared starts at ``SHARED_PRIOR`` and is re-estimated from the association.
``declared_triangles`` turns an association back into the triangle pairs
it implies.

``mapmerge.consensus`` and ``mapmerge.search`` associate with it;
``mapmerge.metrics`` uses it for its oracles.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import ConvexHull, cKDTree

from .alignment import mapped_covariance, paired_transforms, rotation
from .assignment import candidate_components, component_blocks
from .exhaustive import inside_hull
from .triangles import TriangleBatch

#: Log-likelihood margin under which two landmark assignments are
#: indistinguishable (a likelihood ratio below 1,000): triangles on such
#: contested landmarks are not declared, though the landmarks are still
#: fused. Why 1,000 and not 100: docs/tuning.md.
AMBIGUITY = np.log(1000.0)
#: Prior probability π that a q landmark mapped among p's is shared, in the
#: association's unshared hypothesis (and the EM step's mixture): starts here,
#: then is re-estimated from the association (the paired share of q's landmarks
#: inside p's hull over the share the association can pair at that π, see
#: ``associate``) within ``SHARED_RANGE``, ``PRIOR_ROUNDS`` associations in all.
#: The division by that recall keeps the estimate from settling at a
#: self-consistent low value at low SNR (tuning seeds and numbers: docs/tuning.md).
SHARED_PRIOR = 0.8
SHARED_RANGE = (0.1, 0.99)
#: Associations in all; the last is the one returned (see ``associate``).
PRIOR_ROUNDS = 3


def own_covariances(cov, n: int, sigma) -> np.ndarray:
    """The landmarks' covariances, σ² I when none are given: (n, 2, 2), or (B, n, 2, 2) for σ one per map pair."""
    if cov is not None:
        return cov
    sigma = np.asarray(sigma, dtype=float)
    return np.broadcast_to((sigma[..., None, None] ** 2 * np.eye(2))[..., None, :, :], sigma.shape + (n, 2, 2))


def covariance_rows(cov, rows):
    """The optional per-landmark covariances (B, n, 2, 2) of the map pairs ``rows`` (None stays None)."""
    return None if cov is None else cov[rows]


def pair_variances(sigma) -> np.ndarray:
    """2σ² of each σ, computed on Python floats as the one-map-pair code did: Python's ``x**2`` (C's pow)
    differs from numpy's ``x * x`` in the last bit of about one value in a thousand."""
    return np.array([2.0 * float(s)**2 for s in sigma])


def mapped_landmarks(Q, theta, t, cov, sigma, cov_q=None):
    """q's landmarks in p's frame, x = R(θ)ᵀ (q - t), and their covariances there.

    Batched over map pairs: ``Q`` (B, n_q, 2), ``theta`` (B,), ``t`` (B, 2),
    ``cov`` (B, 3, 3) the transform's (θ, t) covariance, ``sigma`` (B,) and
    ``cov_q`` (B, n_q, 2, 2) the landmarks' own noise (σ² I when None).
    Returns x (B, n_q, 2) and cov_x (B, n_q, 2, 2).
    """
    x = (Q - t[:, None, :]) @ rotation(theta)
    own = (np.asarray(sigma, dtype=float) ** 2)[:, None] if cov_q is None else cov_q
    return x, mapped_covariance(x, theta, cov, own)


#: Pairs of landmarks (over a batch of map pairs) whose distances are computed all at once when the
#: candidates of associations are sought; larger maps are searched with a k-d tree, one map pair at a time.
BRUTE_FORCE_PAIRS = 1 << 18


def _close_pairs(P, x, radius):
    """Every (map pair b, p landmark i, x landmark j) with ‖P[b, i] - x[b, j]‖ <= radius[b] (NaN: none)."""
    B, n_p, n_q = P.shape[0], P.shape[1], x.shape[1]
    if n_p * n_q > BRUTE_FORCE_PAIRS:
        found = []
        for b in np.flatnonzero(radius > 0):
            cand = cKDTree(P[b]).sparse_distance_matrix(cKDTree(x[b]), radius[b], output_type="ndarray")
            found.append((np.full(cand.size, b), cand["i"], cand["j"]))
        return tuple(np.concatenate(parts).astype(np.intp) for parts in zip(*found)) if found else \
            (np.empty(0, dtype=np.intp),) * 3
    parts = []
    step = max(1, BRUTE_FORCE_PAIRS // (n_p * n_q))
    for a in range(0, B, step):
        d2 = np.sum((P[a:a + step, :, None, :] - x[a:a + step, None, :, :]) ** 2, axis=-1)
        b, i, j = np.nonzero(d2 <= (radius[a:a + step] ** 2)[:, None, None])
        parts.append((b + a, i, j))
    return tuple(np.concatenate(v).astype(np.intp) for v in zip(*parts))


def _pair_log_odds(P, x, cov_p, cov_x, log_prior):
    """``pair_log_odds`` of B map pairs at once: (b, i, j, log_odds), ``log_prior`` (B,)."""
    det_min = np.linalg.det(cov_p).min(axis=1) + np.linalg.det(cov_x).min(axis=1)
    largest = np.linalg.eigvalsh(cov_p)[..., 1].max(axis=1) + np.linalg.eigvalsh(cov_x)[..., 1].max(axis=1)
    d2_max = 2 * (log_prior - np.log(2 * np.pi * np.sqrt(det_min)))
    radius = np.where(d2_max > 0, np.sqrt(np.maximum(d2_max, 0) * largest), np.nan)
    b, i, j = _close_pairs(P, x, radius)
    C = cov_p[b, i] + cov_x[b, j]
    e = P[b, i] - x[b, j]
    d2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(C), e)
    return b, i, j, -0.5 * d2 - np.log(2 * np.pi * np.sqrt(np.linalg.det(C)))


def pair_log_odds(P, x, cov_p, cov_x, log_prior: float):
    """Every pair that can score > 0 at ``log_prior`` (or any smaller prior), and its score without the prior.

    A pair scores > 0 only if d² < 2 (log_prior - log(2π √det C)), and
    det C >= min det Σp + min det Σx, the largest eigenvalue of C at most the
    sum of the largest ones: that bounds the search radius.

    Returns
    -------
    i, j : (C,) int ndarray
        Candidate pairs (p index, index into x).
    log_odds : (C,) ndarray
        ``log N(P_i - x_j; 0, cov_p[i] + cov_x[j])``.
    """
    _, i, j, log_odds = _pair_log_odds(P[None], x[None], cov_p[None], cov_x[None], np.array([log_prior]))
    return i, j, log_odds


def posterior_association(P, x, cov_p, cov_x, log_prior: float, with_margin: bool = True, candidates=None):
    """The maximum-posterior one-to-one association of P and mapped q landmarks x.

    Pair (i, j) scores its log-odds against "both unshared":
    ``s_ij = log N(P_i - x_j; 0, cov_p[i] + cov_x[j]) + log_prior`` with
    ``log_prior = log(π / (1 - π)) - log λ_q`` (π the prior that a landmark
    is shared, λ_q the density of q landmarks: an unshared one is anywhere).
    Leaving a landmark unpaired scores 0, so a pair is made only when it
    beats both landmarks staying unshared and every competing pair. The total
    score is maximised by an assignment on each connected component of the
    positively scored pairs.

    Parameters
    ----------
    P, x : (n_p, 2), (n_q, 2) ndarray
        p's landmarks and q's mapped into p's frame.
    cov_p, cov_x : (n_p, 2, 2), (n_q, 2, 2) ndarray
        Their covariances in p's frame.
    log_prior : float
    with_margin : bool, default True
        Compute ``margin`` (one more assignment per contested pair: most of
        the cost where many pairs compete).
    candidates : tuple, optional
        ``pair_log_odds(P, x, cov_p, cov_x, L)`` for some ``L >= log_prior``
        (computed once for several priors); by default, for ``log_prior``.

    Returns
    -------
    pairs : (K, 2) int ndarray
        (p index, q index), sorted by p index.
    margin : (K,) ndarray or None
        Score lost if the pair were forbidden and one of its landmarks paired
        otherwise (inf when no competing pairing exists); small margins mark
        pairs the data cannot tell from a swap. None unless ``with_margin``.
    """
    i, j, log_odds = pair_log_odds(P, x, cov_p, cov_x, log_prior) if candidates is None else candidates
    return _assign(i, j, log_odds + log_prior, len(P), len(x), with_margin)


def _assign(i, j, score, n_p: int, n_q: int, with_margin: bool):
    """``posterior_association``'s assignment of scored candidate pairs (i, j) over n_p x n_q landmarks."""
    keep = score > 0
    i, j, score = i[keep], j[keep], score[keep]
    if i.size == 0:
        return np.empty((0, 2), dtype=np.intp), (np.empty(0) if with_margin else None)
    # The common case: a candidate alone in its row and column, a component of its own (no contest).
    single = (np.bincount(i, minlength=n_p)[i] == 1) & (np.bincount(j, minlength=n_q)[j] == 1)
    p_of, q_of, margins = [i[single]], [j[single]], [np.full(int(single.sum()), np.inf)]
    i, j, score = i[~single], j[~single], score[~single]
    comp = candidate_components(i, j, n_p, n_q) if i.size else i
    handled, pairs_2x2, margins_2x2 = _two_by_two(i, j, score, comp, with_margin)
    p_of.append(pairs_2x2[:, 0])
    q_of.append(pairs_2x2[:, 1])
    margins.append(margins_2x2)
    rest = ~handled[comp]
    i, j, score, comp = i[rest], j[rest], score[rest], comp[rest]
    for rows, cols, gain in component_blocks(i, j, score, comp, 0.0):
        r, c = linear_sum_assignment(gain, maximize=True)
        value = gain[r, c]
        keep = value > 0
        p_of.append(rows[r[keep]])
        q_of.append(cols[c[keep]])
        if with_margin:
            margins.append(_margins(gain, r[keep], c[keep], value.sum()))
    pairs = np.stack([np.concatenate(p_of), np.concatenate(q_of)], axis=1).astype(np.intp)
    order = np.argsort(pairs[:, 0], kind="stable")
    return pairs[order], (np.concatenate(margins)[order] if with_margin else None)


def _two_by_two(i, j, score, comp, with_margin: bool):
    """``_assign`` of every component of at most 2 rows and 2 columns at once (most contests: two landmarks
    near one, or two near two), as ``linear_sum_assignment`` and ``_margins`` solve it: of the two
    assignments of a 2 x 2 block (a missing row or column is zeros) the larger total, its positive entries
    kept, and each kept pair's margin from the same choice with that pair zeroed. A component where two
    totals tie is left to the solver, whose choice then decides.

    Returns which components were handled, their pairs and (with ``with_margin``) margins.
    """
    empty = np.zeros(0, dtype=bool), np.empty((0, 2), dtype=np.intp), np.empty(0)
    if not comp.size:
        return empty
    n_comp = int(comp.max()) + 1
    ends = []
    for x in (i, j):
        lo, hi = np.full(n_comp, np.iinfo(np.intp).max), np.full(n_comp, -1)
        np.minimum.at(lo, comp, x)
        np.maximum.at(hi, comp, x)
        ends.append((lo, hi, x != lo[comp]))  # the component's two landmarks and which one x is
    (lo_i, hi_i, r), (lo_j, hi_j, c) = ends
    small = np.bincount(comp, (i != lo_i[comp]) & (i != hi_i[comp]) | (j != lo_j[comp]) & (j != hi_j[comp]),
                        n_comp) == 0
    small &= np.bincount(comp, minlength=n_comp) > 0
    local = np.cumsum(small) - 1
    use = small[comp]
    g = np.zeros((int(small.sum()), 2, 2))
    g[local[comp[use]], r[use].astype(np.intp), c[use].astype(np.intp)] = score[use]
    rows, cols = np.stack([lo_i, hi_i], 1)[small], np.stack([lo_j, hi_j], 1)[small]

    def choose(block):
        """Each block's better assignment: the column of row 0 and of row 1, their entries, and a tie."""
        diagonal, anti = block[:, 0, 0] + block[:, 1, 1], block[:, 0, 1] + block[:, 1, 0]
        diag = diagonal > anti
        columns = np.stack([np.where(diag, 0, 1), np.where(diag, 1, 0)], 1)
        return (columns, np.where(diag, block[:, 0, 0], block[:, 0, 1]), np.where(diag, block[:, 1, 1], block[:, 1, 0]),
                diagonal == anti)

    col_of, v0, v1, tie = choose(g)
    best = v0 + v1  # the assignment's total, as ``value.sum()`` adds it
    kept = np.stack([v0 > 0, v1 > 0], 1)
    margin = np.full(kept.shape, np.inf)
    if with_margin:
        every = np.arange(len(g))
        for a in range(2):
            alt = g.copy()
            alt[every, a, col_of[:, a]] = 0.0
            col2, u0, u1, tie2 = choose(alt)
            tie |= tie2 & kept[:, a]
            used = np.stack([u0 > 0, u1 > 0], 1)
            # Only a re-pairing of row a or of its column is a contest.
            touches = np.any(used & ((np.arange(2) == a) | (col2 == col_of[:, [a]])), axis=1)
            total = np.where(used[:, 0] & used[:, 1], u0 + u1, np.where(used[:, 0], u0, u1))
            margin[:, a] = np.where(touches, best - total, np.inf)
    done = ~tie
    handled = np.zeros(n_comp, dtype=bool)
    handled[np.flatnonzero(small)[done]] = True
    kept &= done[:, None]
    f, a = np.nonzero(kept)
    pairs = np.stack([rows[f, a], cols[f, col_of[f, a]]], 1).astype(np.intp)
    return handled, pairs, margin[f, a]


#: Components of more landmarks (rows or columns) than this get no margins: one assignment per pair would
#: cost O(m⁴) (docs/tuning.md); where so many pairs compete they are contested anyway, and are reported so
#: (margin 0).
MAX_MARGIN_COMPONENT = 300


def _margins(gain, r, c, best):
    """Score lost by forbidding each pair (r, c) of one component's optimal assignment (value ``best``)
    when the best assignment without it re-pairs one of its landmarks, inf otherwise (0 for every pair of a
    component larger than ``MAX_MARGIN_COMPONENT``)."""
    if max(gain.shape) > MAX_MARGIN_COMPONENT:
        return np.zeros(len(r))
    margin = np.full(len(r), np.inf)
    for m, (a, b) in enumerate(zip(r, c)):
        alt = gain.copy()
        alt[a, b] = 0.0
        ra, ca = linear_sum_assignment(alt, maximize=True)
        used = alt[ra, ca] > 0
        # Only a re-pairing of a or b is a contest; both left unshared is not a swap.
        if np.any(used & ((ra == a) | (ca == b))):
            margin[m] = best - alt[ra[used], ca[used]].sum()
    return margin


def associate(P, Q, alignment, sigma, cov_p=None, cov_q=None, hulls=None, with_margin=True):
    """One-to-one landmark association under a fitted transform (``posterior_association``).

    One map pair's ``associate_batch``.

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
    alignment : Alignment
        The fitted transform: anything with ``theta``, ``t`` and ``cov``, the
        covariance of (θ, t) (``metrics.KnownTransform`` for an exact one).
    sigma : float
    cov_p, cov_q : (n, 2, 2) ndarray, optional
    hulls : (ConvexHull, ConvexHull), optional
        The convex hulls of P and Q, when the caller has them (Qhull costs
        about as much as the rest of an association of small maps).
    with_margin : bool, default True
        Find the contested pairs (``posterior_association``'s margins: most of
        its cost where many pairs compete); without, ``contested`` is None.

    Returns
    -------
    pairs : (K, 2) int ndarray
        Landmark pairs (p, q), sorted by p index.
    contested : (K,) bool ndarray or None
        Pairs whose best alternative assignment is within ``AMBIGUITY`` in
        log-likelihood (e.g. two landmarks closer than the noise, which can swap).
    """
    one = (lambda a: None if a is None else np.asarray(a)[None])
    _, pairs, contested = associate_batch(
        P[None], Q[None], np.array([alignment.theta], dtype=float), one(alignment.t), one(alignment.cov),
        np.array([sigma], dtype=float), one(cov_p), one(cov_q), None if hulls is None else [hulls], with_margin)
    return pairs, contested


def associate_batch(P, Q, theta, t, cov, sigma, cov_p=None, cov_q=None, hulls=None, with_margin=True):
    """One-to-one landmark association of B map pairs, each under its own fitted transform.

    The pair covariance is p's noise plus q's brought into p's frame plus the
    fitted transform's error at q_j; landmark noise is σ² I unless
    ``cov_p``/``cov_q`` are given. λ_q is q's landmark count over its convex
    hull's area; π starts at ``SHARED_PRIOR`` and is re-estimated from the
    association (``PRIOR_ROUNDS``), per map pair. The map pairs' landmarks
    are numbered apart, so one assignment problem holds them all and no
    landmark competes with another map pair's.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    theta, t, cov : (B,), (B, 2), (B, 3, 3) ndarray
        Each map pair's transform and its (θ, t) covariance.
    sigma : (B,) ndarray
    cov_p, cov_q : (B, n, 2, 2) ndarray, optional
    hulls : list of (ConvexHull, ConvexHull), optional
        The convex hulls of each P and Q, when the caller has them.
    with_margin : bool, default True
        Find the contested pairs; without, ``contested`` is None.

    Returns
    -------
    trial : (K,) int ndarray
        Map pair of each association.
    pairs : (K, 2) int ndarray
        Landmark pairs (p, q), sorted by map pair, then p index.
    contested : (K,) bool ndarray or None
    """
    B, n_p, n_q = P.shape[0], P.shape[1], Q.shape[1]
    x, cov_x = mapped_landmarks(Q, theta, t, cov, sigma, cov_q)
    cov_p = own_covariances(cov_p, n_p, sigma)
    hulls = [(ConvexHull(P[b]), ConvexHull(Q[b])) for b in range(B)] if hulls is None else hulls
    log_density = np.log(n_q / np.array([hull_q.volume for _, hull_q in hulls]))
    inside = np.stack([inside_hull(hull_p, x[b]) for b, (hull_p, _) in enumerate(hulls)])
    # The pair covariance of each q landmark among p's, with a typical p landmark.
    det_pair = np.linalg.det(cov_x + np.median(cov_p, axis=1)[:, None])
    shared = np.full(B, SHARED_PRIOR)
    # The candidates of the largest prior any round can reach serve every round.
    b, i, j, log_odds = _pair_log_odds(P, x, cov_p, cov_x,
                                       np.log(SHARED_RANGE[1] / (1 - SHARED_RANGE[1])) - log_density)
    i, j = b * n_p + i, b * n_q + j
    for round_ in range(1, PRIOR_ROUNDS + 1):
        log_prior = np.log(shared / (1 - shared)) - log_density
        # Only the association returned needs its margins.
        pairs, margin = _assign(i, j, log_odds + log_prior[b], B * n_p, B * n_q,
                                with_margin and round_ == PRIOR_ROUNDS)
        trial = pairs[:, 0] // n_p
        if round_ == PRIOR_ROUNDS:
            break
        # π re-estimated as the paired share of q's landmarks among p's, over the share of
        # shared ones the association can pair at this π: a true pair scores above "unshared"
        # within the Mahalanobis radius d², which it falls inside with probability 1 - exp(-d²/2).
        d2 = np.maximum(2 * (log_prior[:, None] - np.log(2 * np.pi * np.sqrt(det_pair))), 0.0)
        recall = np.sum(np.where(inside, 1 - np.exp(-d2 / 2), 0.0), axis=1)
        paired = np.bincount(trial, inside.ravel()[pairs[:, 1]], minlength=B)
        shared = np.clip(paired / np.maximum(recall, 1e-9), *SHARED_RANGE)
    pairs = pairs - trial[:, None] * np.array([n_p, n_q])
    return trial, pairs, (margin < AMBIGUITY if with_margin else None)



def declared_triangles(vertices_p, vertices_q, pairs, P, Q, sigma):
    """Triangle pairs whose three landmarks are all associated (``declared_triangles_batch`` of one map pair).

    Parameters
    ----------
    vertices_p, vertices_q : (Tp, 3), (Tq, 3) int ndarray
        Groth-ordered triangles of the two maps.
    pairs : (K, 2) int ndarray
        Landmark associations.

    Returns
    -------
    tri_pairs : (D, 2) int ndarray
        (p triangle, q triangle) index pairs.
    log_lr : (D,) ndarray
        Their log Λ, the q vertices paired with p's Groth order.
    """
    def one(vertices, X):
        return TriangleBatch(X[None], np.asarray(vertices), np.zeros(len(vertices), dtype=np.intp),
                             np.array([0, len(vertices)]))

    _, tri_pairs, log_lr = declared_triangles_batch(one(vertices_p, P), one(vertices_q, Q),
                                                    np.zeros(len(pairs), dtype=np.intp), pairs, np.array([sigma]))
    return tri_pairs, log_lr


#: ``declared_triangles_batch`` keys a q triangle by its map pair and sorted vertices in one int64.
_KEY_LIMIT = 2**62


def declared_triangles_batch(tri_p: TriangleBatch, tri_q: TriangleBatch, trial, pairs, sigma):
    """Triangle pairs of B map pairs whose three landmarks are all associated.

    Parameters
    ----------
    tri_p, tri_q : TriangleBatch
        Groth-ordered triangles of the maps.
    trial, pairs : (K,), (K, 2) int ndarray
        Landmark associations (p index, q index) and their map pair.
    sigma : (B,) ndarray

    Returns
    -------
    tri_trial : (D,) int ndarray
        Map pair of each triangle pair, ascending.
    tri_pairs : (D, 2) int ndarray
        (p triangle, q triangle) index pairs within their map pair, by p triangle.
    log_lr : (D,) ndarray
        Their log Λ, the q vertices paired with p's Groth order.
    """
    P, Q = tri_p.maps, tri_q.maps
    B, n_p, n_q = len(P), P.shape[1], np.int64(Q.shape[1])
    to_q = np.full(B * n_p, -1, dtype=np.int64)
    to_q[trial * n_p + pairs[:, 0]] = pairs[:, 1]
    mapped = to_q[tri_p.flat_vertices()]  # (Sp, 3)
    # One key per q triangle: its map pair and sorted vertices (map pairs in groups whose keys fit an int64).
    per_key = max(1, _KEY_LIMIT // int(n_q) ** 3)

    def key(v, tr):
        v = np.sort(v, axis=1).astype(np.int64)
        return ((v[:, 0] * n_q + v[:, 1]) * n_q + v[:, 2]) + (tr % per_key) * n_q**3

    hits = []
    for a in range(0, B, per_key):
        b = min(a + per_key, B)
        qs = np.arange(tri_q.offsets[a], tri_q.offsets[b])
        kq = key(tri_q.vertices[qs], tri_q.trial[qs])
        order = np.argsort(kq)
        ps = tri_p.offsets[a] + np.flatnonzero(np.all(mapped[tri_p.offsets[a]:tri_p.offsets[b]] >= 0, axis=1))
        kp = key(mapped[ps], tri_p.trial[ps])
        pos = np.clip(np.searchsorted(kq, kp, sorter=order), 0, kq.size - 1)
        hit = kq[order[pos]] == kp
        hits.append((ps[hit], qs[order[pos[hit]]]))
    gp, gq = (np.concatenate(h) for h in zip(*hits))  # p and q triangles, as rows of tri_p and tri_q
    tri_trial = tri_p.trial[gp]
    _, _, cost = paired_transforms(P.reshape(-1, 2)[tri_trial[:, None] * n_p + tri_p.vertices[gp]],
                                   Q.reshape(-1, 2)[tri_trial[:, None] * n_q + mapped[gp]])
    tri_pairs = np.stack([gp - tri_p.offsets[tri_trial], gq - tri_q.offsets[tri_trial]], axis=1)
    return tri_trial, tri_pairs, -cost / pair_variances(sigma)[tri_trial]
