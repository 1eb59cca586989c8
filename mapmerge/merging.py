"""Match and merge two stochastic landmark maps: the whole pipeline.

``merge_maps`` runs the paper's algorithm end to end: triangulate both maps
(Groth order), score every triangle pair with the closed-form GLRT, solve the
assignment LP (14), declare the tentative pairs whose log Λ passes log τ, turn
them into one-to-one landmark correspondences, align with the n-point closed
form and build the combined map (15).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import check_points, check_sigma, check_variances
from .combining import CombinedMap, combine_maps, p_only_map
from .matching import (
    OBJECTIVES, assign, assign_sparse, candidate_pairs, correspondences, resolve_log_tau,
)
from .statistic import Alignment, ccw_order, paired_cost, pairwise_cost
from .triangles import Triangles, _triangulate

#: Matcher variants. "paper": the seed paper (Groth order, LP, τ, eq. 15).
#: "cyclic": the paper with the order-robust statistic (best of the three
#: cyclic vertex orders). "consensus": cyclic statistic + transform-consistent
#: verification + landmark association (mapmerge.verification). "groth" and
#: "astroalign": outside baselines (mapmerge.baselines).
METHODS = ("paper", "cyclic", "consensus", "groth", "astroalign")
#: Methods that score triangle pairs with the GLRT and solve the LP.
LP_METHODS = ("paper", "cyclic", "consensus")

#: Fewest landmark correspondences accepted as a match: one triangle's worth.
MIN_MATCHED_LANDMARKS = 3

#: Default threshold: reject 1 % of true, order-consistent triangle pairs.
DEFAULT_TAU = "chi2:0.01"

#: Above this many triangle pairs (Tp·Tq, about 250 landmarks per map)
#: merge_maps switches to the sparse, gated path.
DENSE_MAX_PAIRS = 250_000
#: Candidate q triangles kept per p triangle on the sparse path (nearest in
#: side-length space within the gate).
SPARSE_NEIGHBOURS = 8


@dataclass(frozen=True)
class MergeResult:
    """Outcome of ``merge_maps``.

    Attributes
    ----------
    matched : bool
        False when no triangle pair passed τ ("no match"): then ``theta`` and
        ``t`` are NaN, ``alignment`` is None and ``merged`` is map p alone.
    theta : float
        Rotation of map q relative to map p (``q ≈ R(θ) p + t``).
    t : (2,) ndarray
        Translation.
    pairs : (K, 2) int ndarray
        Landmark correspondences (p index, q index).
    n_conflicts : int
        Correspondences dropped because a landmark was claimed twice.
    triangle_pairs : (M, 2) int ndarray
        Tentative triangle pairs from the LP (indices into ``tri_p``/``tri_q``).
    triangle_log_lr : (M,) ndarray
        Their log Λ.
    declared : (M,) bool ndarray
        ``triangle_log_lr >= log_tau``.
    log_tau : float
        The threshold used, as a log-LR.
    merged : (N, 2) ndarray
        The combined map in p's frame; ``origin``, ``index_p``, ``index_q``
        give each row's provenance.
    """

    matched: bool
    theta: float
    t: np.ndarray
    pairs: np.ndarray
    n_conflicts: int
    triangle_pairs: np.ndarray
    triangle_log_lr: np.ndarray
    declared: np.ndarray
    log_tau: float
    tri_p: Triangles
    tri_q: Triangles
    alignment: Alignment | None
    combined: CombinedMap
    method: str = "paper"

    @property
    def merged(self) -> np.ndarray:
        return self.combined.points

    @property
    def origin(self) -> np.ndarray:
        return self.combined.origin

    @property
    def index_p(self) -> np.ndarray:
        return self.combined.index_p

    @property
    def index_q(self) -> np.ndarray:
        return self.combined.index_q

    @property
    def cov(self) -> np.ndarray:
        """(N, 2, 2) covariance of each combined-map row."""
        return self.combined.cov


def merge_maps(P, Q, sigma, tau=DEFAULT_TAU, method="paper", objective="lr",
               var_p=None, var_q=None) -> MergeResult:
    """Match two landmark maps and build their maximum-likelihood combination.

    Parameters
    ----------
    P, Q : (n, 2) array_like
        Landmark estimates of map p and map q, each in its own frame; n >= 3,
        finite, distinct, not all collinear.
    sigma : float
        Known per-coordinate noise standard deviation, > 0.
    tau : float or str, default ``"chi2:0.01"``
        Threshold: a log-LR value, or ``"chi2:P"`` for the χ²₃ rule
        ``log τ = -½ χ²₃⁻¹(1 - P)``.
    method : {"paper", "cyclic", "consensus", "groth", "astroalign"}
        Matcher variant (see ``METHODS``); "astroalign" needs the optional
        ``astroalign`` package.
    objective : {"lr", "loglr"}
        LP objective: Σ Λ as in the paper, or Σ log Λ.
    var_p, var_q : (n,) array_like, optional
        Per-landmark variances (per coordinate, e.g. half the trace of each
        landmark's covariance) for ``method="consensus"``: its landmark
        association gates and significance test use them instead of σ².

    Returns
    -------
    MergeResult

    Raises
    ------
    ValueError
        On invalid maps, ``sigma``, ``tau``, ``method``, ``objective`` or
        variances.
    """
    P = check_points(P, "P")
    Q = check_points(Q, "Q")
    sigma = check_sigma(sigma)
    var_p, var_q = check_variances(var_p, len(P), "var_p"), check_variances(var_q, len(Q), "var_q")
    log_tau = resolve_log_tau(tau)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")

    if method not in LP_METHODS:
        from .baselines import BASELINES

        return BASELINES[method](P, Q, sigma)
    # On the sparse path the consensus step needs every gated candidate, not
    # only the LP's choice: at scale chance congruences outbid most true pairs.
    match = match_triangles(P, Q, sigma, objective, cyclic=method != "paper", log_tau=log_tau,
                            solve_lp=method != "consensus")
    return merge_at(P, Q, sigma, match, log_tau, method, var_p, var_q)


@dataclass(frozen=True)
class TriangleMatch:
    """Triangles of both maps and the LP's tentative pairs with their scores.

    ``p_vertices[m]`` and ``q_vertices[m]`` are the landmarks of pair m's
    triangles, paired vertex by vertex: Groth order for the paper's
    statistic, the best orientation-preserving correspondence for the
    order-robust one.
    """

    tri_p: Triangles
    tri_q: Triangles
    triangle_pairs: np.ndarray
    triangle_log_lr: np.ndarray
    p_vertices: np.ndarray
    q_vertices: np.ndarray


def match_triangles(
    P: np.ndarray, Q: np.ndarray, sigma: float, objective: str, cyclic: bool = False,
    log_tau: float | None = None, sparse: bool | None = None, solve_lp: bool = True,
) -> TriangleMatch:
    """Triangulate, score the triangle pairs and solve the LP (inputs already valid).

    The τ-independent part of ``merge_maps``: callers comparing several
    thresholds on one map pair run it once and ``merge_at`` per τ.

    Dense path: every pair is scored (Tp x Tq matrix) and the LP is solved
    exactly. Sparse path (``sparse=True``, or automatically when
    Tp·Tq > ``DENSE_MAX_PAIRS`` and a finite ``log_tau`` is given): only
    pairs within the side-length gate of ``log_tau`` (``gate_radius``, at
    most ``SPARSE_NEIGHBOURS`` per p triangle) are scored and the LP is
    solved on that sparse graph, so memory grows like n and time like
    n log n. It declares the same pairs as the dense path unless the
    neighbour cap, or a pair outside the gate (Λ < τ) competing in the LP,
    changes the LP's choice (tested equal on maps where both run). With
    ``solve_lp=False`` the sparse path returns every candidate passing log τ
    as tentative pairs.
    """
    tri_p, tri_q = _triangulate(P), _triangulate(Q)
    vp, vq = tri_p.vertices, tri_q.vertices
    if cyclic:
        vp = np.take_along_axis(vp, ccw_order(tri_p.coords), axis=1)
        vq = np.take_along_axis(vq, ccw_order(tri_q.coords), axis=1)
    finite_tau = log_tau is not None and np.isfinite(log_tau)
    if sparse is None:
        sparse = finite_tau and len(vp) * len(vq) > DENSE_MAX_PAIRS
    if sparse and not finite_tau:
        raise ValueError("the sparse path needs a finite threshold tau")
    if sparse:
        cand = candidate_pairs(P[vp], Q[vq], sigma, log_tau, SPARSE_NEIGHBOURS)
        cost, shift = paired_cost(P[vp[cand[:, 0]]], Q[vq[cand[:, 1]]], cyclic)
        if solve_lp:
            chosen = assign_sparse(-cost / (2.0 * sigma**2), cand, (len(vp), len(vq)), objective)
        else:  # every candidate that can be declared
            keep = -cost / (2.0 * sigma**2) >= log_tau
            cand, cost, shift = cand[keep], cost[keep], shift[keep]
            chosen = cand
        # Map the chosen pairs back to their candidate rows (both sorted by p index).
        at = np.searchsorted(cand[:, 0] * len(vq) + cand[:, 1], chosen[:, 0] * len(vq) + chosen[:, 1])
        triangle_pairs, scores, shifts = chosen, -cost[at] / (2.0 * sigma**2), shift[at]
    else:
        cost, shift = pairwise_cost(P[vp], Q[vq], cyclic)
        log_lr = -cost / (2.0 * sigma**2)
        triangle_pairs = assign(log_lr, objective)
        i, j = triangle_pairs[:, 0], triangle_pairs[:, 1]
        scores, shifts = log_lr[i, j], shift[i, j]
    i, j = triangle_pairs[:, 0], triangle_pairs[:, 1]
    roll = (np.arange(3)[None, :] + shifts[:, None]) % 3
    q_vertices = np.take_along_axis(vq[j], roll, axis=1)
    return TriangleMatch(tri_p, tri_q, triangle_pairs, scores, vp[i], q_vertices)


def merge_at(
    P: np.ndarray, Q: np.ndarray, sigma: float, match: TriangleMatch, log_tau: float,
    method: str = "paper", var_p=None, var_q=None,
) -> MergeResult:
    """Declare, associate landmarks and combine at one threshold log τ."""
    if method == "consensus":
        from .verification import consensus_merge

        return consensus_merge(P, Q, sigma, match, log_tau, var_p, var_q)
    scores = match.triangle_log_lr
    declared = scores >= log_tau
    pairs, n_conflicts = correspondences(
        match.p_vertices[declared], match.q_vertices[declared], scores[declared]
    )
    return finish(P, Q, sigma, pairs, n_conflicts, match.triangle_pairs, scores, declared,
                  log_tau, match.tri_p, match.tri_q, method)


def finish(P, Q, sigma, pairs, n_conflicts, triangle_pairs, scores, declared, log_tau,
           tri_p, tri_q, method) -> MergeResult:
    """Align on the landmark pairs and build the result (no match below 3 pairs)."""
    if pairs.shape[0] < MIN_MATCHED_LANDMARKS:
        alignment, combined = None, p_only_map(P, sigma)
        theta, t = float("nan"), np.full(2, np.nan)
    else:
        alignment, combined = combine_maps(P, Q, pairs, sigma)
        theta, t = alignment.theta, alignment.t
    return MergeResult(
        matched=alignment is not None,
        theta=theta,
        t=t,
        pairs=pairs,
        n_conflicts=n_conflicts,
        triangle_pairs=triangle_pairs,
        triangle_log_lr=scores,
        declared=declared,
        log_tau=log_tau,
        tri_p=tri_p,
        tri_q=tri_q,
        alignment=alignment,
        combined=combined,
        method=method,
    )
