"""Consensus verification and landmark association (beyond the paper, DESIGN §5).

True triangle matches all share one rigid motion (θ, t); chance congruences
between unrelated triangles do not. ``consensus_merge``:

1. takes the LP's tentative pairs that pass log τ (order-robust statistic)
   as hypotheses, each with its own closed-form (θ_h, t_h);
2. counts, for every hypothesis, the candidate pairs whose three vertices it
   maps onto their partners within a χ²₆ gate. The gate's variance is the
   noise of both maps plus the hypothesis's own uncertainty at each vertex
   (translation and rotation error of a 3-point fit), so tolerances come
   from σ, not from hand-tuned constants;
3. keeps the largest transform-consistent set (at least
   ``MIN_CONSENSUS`` triangle pairs, otherwise "no match"), refits with the
   n-point closed form, then associates *every* landmark one-to-one under
   the fitted transform with a χ²₂ gate on the Mahalanobis distance
   (assignment per connected component of the gated candidate graph), and
   refits on all associations (``ASSOCIATION_ROUNDS`` times), and accepts
   the match only if chance would rarely produce one as good
   (``match_nfa``, an a contrario test);
4. declares every triangle pair whose three landmarks are associated, so
   common landmarks appear once in the combined map.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, cKDTree
from scipy.special import gammaln
from scipy.stats import chi2

from .matching import correspondences
from .statistic import _J, _align, mapped_covariance, paired_transforms, rotation

#: Tail probability of every χ² gate (a true pair / landmark is rejected
#: with this probability).
GATE_P = 1e-3
#: Fewest transform-consistent triangle pairs accepted as a match: a single
#: chance congruence is common, two agreeing on one transform are not.
MIN_CONSENSUS = 2
#: Hypotheses scored against all candidates (the best-scoring pairs).
MAX_HYPOTHESES = 256
#: A match is accepted when its number of false alarms (``match_nfa``: the
#: expected number of equally good chance matches among the hypotheses
#: tried) is at most this. Unrelated maps therefore give "no match".
MATCH_NFA = 1e-3
#: Hypotheses (most inliers first) refitted on their inliers and recounted.
REFINE = 8
#: Refit-and-associate rounds after the consensus fit.
ASSOCIATION_ROUNDS = 2


def _gate_d2(cp, cq, theta, t, var):
    """χ²₆-distributed misfit of paired triangles under one or many transforms."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    pred = np.einsum("...ij,mvj->...mvi", R, cp) + np.expand_dims(t, (-3, -2))
    return np.sum(np.sum((cq - pred) ** 2, axis=-1) / var, axis=-1)


def _consensus(vp, vq, P, Q, scores, sigma):
    """Index set of the largest transform-consistent group of candidate pairs.

    Every candidate's own 3-point transform is a hypothesis; its inliers are
    gated with the hypothesis's uncertainty (loose for small triangles). The
    ``REFINE`` best hypotheses are then refitted on their inliers' landmarks
    and recounted with the refit's much smaller uncertainty, which is what
    separates the true group from loose chance groups.
    """
    cp, cq = P[vp], Q[vq]
    gate = chi2.isf(GATE_P, 6)
    hyp = np.argsort(-scores, kind="stable")[:MAX_HYPOTHESES]
    theta, t, _ = paired_transforms(cp[hyp], cq[hyp])
    centre = cp[hyp].mean(axis=1)
    spread = np.sum((cp[hyp] - centre[:, None]) ** 2, axis=(1, 2))  # Σ‖p̃‖²
    lever2 = np.sum((cp[None] - centre[:, None, None, :]) ** 2, axis=-1)  # (H, M, 3)
    # Per coordinate: both maps' noise, t at the centroid (2σ²/3) and the
    # rotation error 2σ²/Σ‖p̃‖² times the squared lever arm.
    var = 2 * sigma**2 * (1 + 1 / 3 + lever2 / spread[:, None, None])
    inliers = _gate_d2(cp, cq, theta, t, var) <= gate
    count = inliers.sum(axis=1)
    best, best_key = np.empty(0, dtype=np.intp), (0, 0.0)
    for h in np.lexsort((-scores[hyp], -count))[:REFINE]:
        if count[h] < MIN_CONSENSUS:
            break
        pairs, _ = correspondences(vp[inliers[h]], vq[inliers[h]], scores[inliers[h]])
        if pairs.shape[0] < 3:
            continue
        al = _align(P[pairs[:, 0]], Q[pairs[:, 1]], sigma)
        var_fit = 2 * sigma**2 + _prediction_var(cp, al)
        members = np.flatnonzero(_gate_d2(cp, cq, al.theta, al.t, var_fit) <= gate)
        key = (members.size, float(scores[members].sum()))
        if key > best_key:
            best, best_key = members, key
    return best


def _prediction_var(points, alignment):
    """Mean per-coordinate variance of R(θ) x + t from the fit's covariance."""
    R = rotation(alignment.theta)
    G = np.concatenate([(points @ (R @ _J).T)[..., None], np.broadcast_to(np.eye(2), points.shape + (2,))], -1)
    return 0.5 * np.einsum("...ij,jk,...ik->...", G, alignment.cov, G)


def associate(P, Q, alignment, sigma):
    """One-to-one landmark association under a fitted transform.

    Each pair (i, j) with Mahalanobis distance
    ``d² = eᵀ (σ² I + Σ_xj)⁻¹ e``, ``e = p_i - R(θ)ᵀ (q_j - t)``, below the
    χ²₂ gate is a candidate; the assignment minimising Σ d² is solved on
    each connected component of the candidate graph.

    Returns
    -------
    (K, 2) int ndarray
        Landmark pairs (p, q), sorted by p index.
    """
    x = (Q - alignment.t) @ rotation(alignment.theta)
    cov = mapped_covariance(x, alignment.theta, alignment.cov, sigma) + sigma**2 * np.eye(2)
    gate = chi2.isf(GATE_P, 2)
    radius = np.sqrt(gate * np.linalg.eigvalsh(cov)[:, 1].max())
    cand = cKDTree(P).sparse_distance_matrix(cKDTree(x), radius, output_type="coo_matrix")
    i, j = cand.row, cand.col
    e = P[i] - x[j]
    d2 = np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov[j]), e)
    ok = d2 <= gate
    i, j, d2 = i[ok], j[ok], d2[ok]
    if i.size == 0:
        return np.empty((0, 2), dtype=np.intp)
    n_p = P.shape[0]
    graph = coo_matrix((np.ones(i.size), (i, n_p + j)), shape=(n_p + len(Q),) * 2)
    _, label = connected_components(graph, directed=False)
    comp = label[i]
    sizes = np.bincount(comp)
    single = sizes[comp] == 1  # the common case: one candidate, no contest
    pairs = [np.stack([i[single], j[single]], axis=1)]
    for k in np.unique(comp[~single]):
        sel = comp == k
        rows, ri = np.unique(i[sel], return_inverse=True)
        cols, ci = np.unique(j[sel], return_inverse=True)
        cost = np.full((rows.size, cols.size), 2 * gate + 1.0)
        cost[ri, ci] = d2[sel]
        r, c = linear_sum_assignment(cost)
        keep = cost[r, c] <= gate
        pairs.append(np.stack([rows[r[keep]], cols[c[keep]]], axis=1))
    pairs = np.concatenate(pairs).astype(np.intp)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def match_nfa(P, Q, alignment, pairs, n_hypotheses: int, sigma: float) -> float:
    """Number of false alarms of a match, a contrario (Moisan & Stival 2004).

    Under "unrelated maps", a q landmark mapped inside map p's hull finds a p
    landmark within Mahalanobis radius d² by chance with probability
    ``α(d²) = ρ_p · π · √det C · d²`` (ρ_p the landmark density of p, C the
    gate covariance). For the k tightest associations, the 3 that fix a
    hypothesis excepted, chance gives them with probability at most
    ``C(N, k - 3) α(d²_(k))^(k-3)`` among the N landmarks inside the hull;
    with ``n_hypotheses`` hypotheses tried, NFA is the smallest
    ``n_hypotheses · C(N, k - 3) · α(d²_(k))^(k-3)`` over k. A match with
    NFA <= ``MATCH_NFA`` is expected to arise by chance at most that often.
    """
    x = (Q - alignment.t) @ rotation(alignment.theta)
    cov = mapped_covariance(x, alignment.theta, alignment.cov, sigma) + sigma**2 * np.eye(2)
    hull = ConvexHull(P)
    inside = np.all(x @ hull.equations[:, :2].T + hull.equations[:, 2] <= 0, axis=1)
    density = P.shape[0] / hull.volume  # a 2-D hull's "volume" is its area
    unit_area = density * np.pi * np.sqrt(np.linalg.det(cov[inside | np.isin(np.arange(len(Q)), pairs[:, 1])])).mean()
    e = P[pairs[:, 0]] - x[pairs[:, 1]]
    d2 = np.sort(np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov[pairs[:, 1]]), e))
    n_in = max(int(inside.sum()), len(pairs))
    k = np.arange(4, len(pairs) + 1)
    free = k - 3
    alpha = np.minimum(1.0, unit_area * d2[k - 1])
    log_comb = gammaln(n_in + 1) - gammaln(free + 1) - gammaln(n_in - free + 1)
    log_nfa = np.log(n_hypotheses) + log_comb + free * np.log(np.maximum(alpha, 1e-300))
    return float(np.exp(log_nfa.min())) if k.size else float(n_hypotheses)


def declared_triangles(match, pairs, P, Q, sigma):
    """Triangle pairs whose three landmarks are all associated.

    Returns the (p triangle, q triangle) index pairs, the q vertices in the
    order paired with p's Groth order, and their log Λ.
    """
    to_q = np.full(P.shape[0], -1, dtype=np.int64)
    to_q[pairs[:, 0]] = pairs[:, 1]
    mapped = to_q[match.tri_p.vertices]  # (Tp, 3)
    full = np.all(mapped >= 0, axis=1)
    n_q = np.int64(Q.shape[0])

    def key(v):
        v = np.sort(v, axis=1).astype(np.int64)
        return (v[:, 0] * n_q + v[:, 1]) * n_q + v[:, 2]

    kq = key(match.tri_q.vertices)
    order = np.argsort(kq)
    tp_idx = np.flatnonzero(full)
    kp = key(mapped[tp_idx])
    pos = np.clip(np.searchsorted(kq, kp, sorter=order), 0, kq.size - 1)
    hit = kq[order[pos]] == kp
    tri_pairs = np.stack([tp_idx[hit], order[pos[hit]]], axis=1)
    q_vertices = mapped[tri_pairs[:, 0]]
    _, _, cost = paired_transforms(P[match.tri_p.vertices[tri_pairs[:, 0]]], Q[q_vertices])
    return tri_pairs, q_vertices, -cost / (2.0 * sigma**2)


def consensus_merge(P, Q, sigma, match, log_tau):
    """The ``method="consensus"`` merge (inputs already valid).

    Parameters
    ----------
    P, Q : ndarray
        The maps.
    sigma : float
    match : TriangleMatch
        LP output with the order-robust statistic.
    log_tau : float
        Threshold for a tentative pair to become a hypothesis / candidate.

    Returns
    -------
    MergeResult
        ``triangle_pairs`` holds the declared pairs (all three landmarks
        associated) followed by the LP's remaining tentative pairs.
    """
    from .merging import finish

    cand = np.flatnonzero(match.triangle_log_lr >= log_tau)
    vp = match.p_vertices[cand]
    vq = match.q_vertices[cand]
    scores = match.triangle_log_lr[cand]
    pairs, n_conflicts = np.empty((0, 2), dtype=np.intp), 0
    if cand.size >= MIN_CONSENSUS:
        group = _consensus(vp, vq, P, Q, scores, sigma)
        if group.size >= MIN_CONSENSUS:
            pairs, n_conflicts = correspondences(vp[group], vq[group], scores[group])
    if pairs.shape[0] < 3:
        none = np.zeros(match.triangle_pairs.shape[0], dtype=bool)
        return finish(P, Q, sigma, np.empty((0, 2), dtype=np.intp), n_conflicts,
                      match.triangle_pairs, match.triangle_log_lr, none, log_tau,
                      match.tri_p, match.tri_q, "consensus")
    for _ in range(ASSOCIATION_ROUNDS):
        alignment = _align(P[pairs[:, 0]], Q[pairs[:, 1]], sigma)
        pairs = associate(P, Q, alignment, sigma)
        if pairs.shape[0] < 3:
            break
    if pairs.shape[0] >= 3:
        alignment = _align(P[pairs[:, 0]], Q[pairs[:, 1]], sigma)
        if match_nfa(P, Q, alignment, pairs, cand.size, sigma) > MATCH_NFA:
            pairs = np.empty((0, 2), dtype=np.intp)
    tri_pairs, _, tri_scores = declared_triangles(match, pairs, P, Q, sigma)
    # Keep the LP's other tentative pairs (undeclared) so that their labels
    # still count as misses or true negatives.
    n_tq = len(match.tri_q)
    rest = ~np.isin(match.triangle_pairs @ [n_tq, 1], tri_pairs @ [n_tq, 1])
    all_pairs = np.concatenate([tri_pairs, match.triangle_pairs[rest]]).astype(np.intp)
    all_scores = np.concatenate([tri_scores, match.triangle_log_lr[rest]])
    declared = np.r_[np.ones(len(tri_pairs), bool), np.zeros(int(rest.sum()), bool)]
    return finish(P, Q, sigma, pairs, n_conflicts, all_pairs, all_scores, declared, log_tau,
                  match.tri_p, match.tri_q, "consensus")
