"""Triangle matching: the τ test and the driver ``match_triangles``.

``match_triangles`` triangulates a batch of map pairs, scores their
triangle pairs with the GLRT and solves each pair's assignment LP (14)
(``mapmerge.assignment``). Only the Delaunay calls and the LP run per map
pair. On large maps only the triangle pairs within a side-length gate of
the loosest threshold are scored (``candidate_pairs``, ``gate_radius``),
and the LP is solved on that sparse graph.

The threshold τ is a log-LR value or a χ²₃ rule (``resolve_log_tau``,
``log_tau_from_chi2``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.special import chdtri

from .assignment import assign_sparse, lp_weight
from .statistic import log_lr_from_cost, min_cost, pairwise_log_lr_blocks
from .triangles import PARALLEL_MIN_LANDMARKS, TriangleBatch, triangulate_batches, z_order

#: Degrees of freedom of -2 log Λ for a true triangle pair (2n - 3, n = 3).
TRIANGLE_DOF = 3


@functools.lru_cache(maxsize=256)
def log_tau_from_chi2(p_miss: float, dof: int = TRIANGLE_DOF) -> float:
    """Threshold log τ that rejects a fraction ``p_miss`` of true pairs.

    Under H1, ``-2 log Λ ~ χ²_dof``, so ``log τ = -½ χ²_dof⁻¹(1 - p_miss)``.
    """
    if not 0.0 < p_miss < 1.0:
        raise ValueError(f"tau chi2 tail probability must be in (0, 1), got {p_miss!r}")
    return -0.5 * float(chdtri(dof, p_miss))  # χ²_dof⁻¹(1 - p_miss); scipy.stats is slow to import


def resolve_log_tau(tau) -> float:
    """Turn a threshold setting into a log-likelihood-ratio value.

    Parameters
    ----------
    tau : float or str
        A number is log τ itself (a log-LR, normally <= 0; ``-inf`` declares
        every tentative pair). A string ``"chi2:P"`` is a χ²₃ tail
        probability P in (0, 1): the fraction of true, order-consistent
        triangle pairs the test may reject.

    Returns
    -------
    float

    Raises
    ------
    ValueError
        If ``tau`` is neither form.
    """
    bad = f"tau must be a log-LR number or 'chi2:P' with P in (0, 1), got {tau!r}"
    if isinstance(tau, str) and tau.strip().startswith("chi2:"):
        try:
            p = float(tau.strip()[len("chi2:"):])
        except ValueError:
            raise ValueError(bad) from None
        return log_tau_from_chi2(p)
    try:
        value = float(tau)
    except (TypeError, ValueError):
        raise ValueError(bad) from None
    if np.isnan(value) or value == np.inf:
        raise ValueError(bad)
    return value


def side_features(coords: np.ndarray) -> np.ndarray:
    """Sorted side lengths (T, 3): invariant to rotation, translation and vertex order."""
    sides = np.linalg.norm(coords - np.roll(coords, -1, axis=1), axis=2)
    return np.sort(sides, axis=1)


def gate_radius(sigma: float, log_tau: float) -> float:
    """Side-feature distance that no pair with log Λ >= log τ can exceed.

    After the optimal alignment each vertex leaves a residual r_v with
    Σ‖r_v‖² = 2J*, and each paired side differs by at most ‖r_a‖ + ‖r_b‖,
    so the side vectors differ by at most √(8 J*); sorting both can only
    shrink that. A declared pair has J* <= -2σ² log τ, hence the radius
    ``4σ √(-log τ)``: the gate loses no pair the threshold would keep.
    """
    return 4.0 * sigma * np.sqrt(max(-log_tau, 0.0))


def candidate_pairs(coords_p, coords_q, sigma: float, log_tau: float, k: int):
    """Triangle pairs within the side-feature gate, at most ``k`` per p triangle.

    Returns
    -------
    (C, 2) int ndarray
        Candidate (p triangle, q triangle) pairs, sorted by (p, q). The cap
        ``k`` keeps the nearest in feature space; below it the gate is
        complete (``gate_radius``).
    """
    tree = cKDTree(side_features(coords_q))
    k = min(k, len(coords_q))
    large = len(coords_p) >= 2 * PARALLEL_MIN_LANDMARKS  # a map has about 2n triangles
    features = side_features(coords_p)
    # Queried along a Z-order curve of the features, neighbouring queries walk the same tree nodes while
    # they are in cache (a quarter of the CPU at 2·10^6 triangles); each row's answer is its own.
    order = z_order(features) if large else slice(None)
    dist, idx = np.empty((len(coords_p), k)), np.empty((len(coords_p), k), dtype=np.intp)
    found = tree.query(features[order], k=k, distance_upper_bound=gate_radius(sigma, log_tau),
                       workers=-1 if large else 1)
    dist[order], idx[order] = (a.reshape(len(coords_p), k) for a in found)
    # Sorted within each row (neighbours the gate left out last): rows come in order, so pairs are by (p, q).
    idx = np.where(np.isfinite(dist), idx, len(coords_q))
    idx.sort(axis=1)
    rows, slot = np.nonzero(idx < len(coords_q))
    return np.stack([rows, idx[rows, slot]], axis=1).astype(np.intp)

#: Above this many triangle pairs (Tp·Tq, about 250 landmarks per map) the
#: driver switches to the sparse, gated path when given a finite threshold.
DENSE_MAX_PAIRS = 250_000
#: Candidate q triangles kept per p triangle on the sparse path (nearest in
#: side-length space within the gate).
SPARSE_NEIGHBOURS = 8


@dataclass(frozen=True)
class TriangleMatch:
    """Triangles of a batch of map pairs and the tentative triangle pairs.

    Attributes
    ----------
    tri_p, tri_q : TriangleBatch
        Triangles of the B maps p and q (Groth order).
    trial : (M,) int ndarray
        Map pair of each tentative pair (sorted).
    triangle_pairs : (M, 2) int ndarray
        (p triangle, q triangle), indices within their own map.
    log_lr : (M,) ndarray
        Their log Λ.
    p_vertices, q_vertices : (M, 3) int ndarray
        Landmarks of the pair's triangles paired vertex by vertex: Groth
        order for the paper's statistic, the best orientation-preserving
        correspondence for the order-robust one.
    """

    tri_p: TriangleBatch
    tri_q: TriangleBatch
    trial: np.ndarray
    triangle_pairs: np.ndarray
    log_lr: np.ndarray
    p_vertices: np.ndarray
    q_vertices: np.ndarray

    def __len__(self) -> int:
        return len(self.tri_p)

    def take(self, trials: np.ndarray) -> "TriangleMatch":
        """The map pairs ``trials`` (indices, increasing), renumbered 0..len(trials)-1."""
        renumber = np.full(len(self), -1)
        renumber[trials] = np.arange(len(trials))
        keep = renumber[self.trial] >= 0
        return TriangleMatch(self.tri_p.take(trials), self.tri_q.take(trials), renumber[self.trial[keep]],
                             self.triangle_pairs[keep], self.log_lr[keep], self.p_vertices[keep],
                             self.q_vertices[keep])


def match_triangles(P: np.ndarray, Q: np.ndarray, sigma: np.ndarray, objective: str = "lr",
                    cyclic: bool = False, log_tau: float | None = None, sparse: bool | None = None,
                    solve_lp: bool = True) -> TriangleMatch:
    """Triangulate, score the triangle pairs and solve the LP of B map pairs.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
        Valid maps (not re-checked).
    sigma : (B,) ndarray
        Noise standard deviation of each map pair.
    objective : {"lr", "loglr"}
    cyclic : bool
        Order-robust statistic (best orientation-preserving correspondence).
    log_tau : float, optional
        The loosest threshold that will be applied; enables the sparse path.
    sparse : bool, optional
        Dense path: every pair is scored and the LP solved exactly. Sparse
        path (``sparse=True``, or automatically when Tp·Tq >
        ``DENSE_MAX_PAIRS`` and a finite ``log_tau`` is given): only pairs
        within the side-length gate of ``log_tau`` (``gate_radius``, at most
        ``SPARSE_NEIGHBOURS`` per p triangle) are scored and the LP is solved
        on that sparse graph, so memory grows like n and time like n log n.
        It declares the same pairs as the dense path unless the neighbour
        cap, or a pair outside the gate (Λ < τ) competing in the LP, changes
        the LP's choice.
    solve_lp : bool
        With ``False`` the sparse path returns every gated candidate passing
        ``log_tau`` as tentative pairs (what consensus verification wants:
        at scale, chance congruences outbid most true pairs in the LP).

    Returns
    -------
    TriangleMatch
    """
    tri_p, tri_q = triangulate_batches(P, Q)
    vp = tri_p.ccw_vertices() if cyclic else tri_p.vertices
    vq = tri_q.ccw_vertices() if cyclic else tri_q.vertices
    finite_tau = log_tau is not None and np.isfinite(log_tau)
    if sparse is None:
        sparse = finite_tau and int(np.max(tri_p.count * tri_q.count)) > DENSE_MAX_PAIRS
    if sparse and not finite_tau:
        raise ValueError("the sparse path needs a finite threshold tau")
    if sparse:
        options = _SparseOptions(objective, cyclic, log_tau, solve_lp)
        parts = [_sparse_pairs(tri_p, tri_q, vp, vq, b, float(sigma[b]), options) for b in range(len(tri_p))]
        trial = np.repeat(np.arange(len(parts)), [len(p[0]) for p in parts])
        i, j, score, shift = (np.concatenate([p[k] for p in parts]) for k in range(4))
    else:
        trial, i, j, score, shift = _dense_pairs(tri_p, tri_q, vp, vq, sigma, objective, cyclic)
    gp, gq = tri_p.offsets[trial] + i, tri_q.offsets[trial] + j
    q_vertices = vq[gq]
    if cyclic:  # q vertex (v + shift) % 3 pairs with p vertex v
        q_vertices = q_vertices[np.arange(len(gq))[:, None], (np.arange(3) + shift[:, None].astype(np.intp)) % 3]
    return TriangleMatch(tri_p, tri_q, trial, np.stack([i, j], axis=1).astype(np.intp), score, vp[gp], q_vertices)


def _dense_pairs(tri_p, tri_q, vp, vq, sigma, objective, cyclic):
    """Per map pair, the LP (14) on all its triangle pairs: (trial, i, j, log Λ, shift) of the
    tentative pairs of every map pair, in map-pair order.

    Solved block by block as the scores come, so that memory stays at one
    block's whatever the number of map pairs (no (B, Tp, Tq) array of scores
    or weights is ever held).
    """
    parts = []
    for trials, log_lr, shift in pairwise_log_lr_blocks(tri_p, tri_q, vp, vq, sigma, cyclic):
        weight = lp_weight(log_lr, objective)
        solved = [linear_sum_assignment(weight[k, :tp, :tq], maximize=True)
                  for k, (tp, tq) in enumerate(zip(tri_p.count[trials].tolist(), tri_q.count[trials].tolist()))]
        k = np.repeat(np.arange(len(trials)), [len(i) for i, _ in solved])
        i, j = np.concatenate([i for i, _ in solved]), np.concatenate([j for _, j in solved])
        parts.append((trials[k], i, j, log_lr[k, i, j], shift[k, i, j]))
    trial, i, j, score, shift = (np.concatenate([p[c] for p in parts]) for c in range(5))
    # Blocks group map pairs by triangle count; a stable sort restores map-pair order
    # and keeps each one's pairs in the LP's order.
    order = np.argsort(trial, kind="stable")
    return trial[order], i[order], j[order], score[order], shift[order]


@dataclass(frozen=True)
class _SparseOptions:
    """``match_triangles``' options that the sparse path of every map pair shares."""

    objective: str
    cyclic: bool
    log_tau: float
    solve_lp: bool


def _sparse_pairs(tri_p, tri_q, vp, vq, b, sigma, options: _SparseOptions):
    """(i, j, log Λ, shift) of the tentative pairs of map pair ``b`` on the gated sparse graph."""
    objective, cyclic, log_tau = options.objective, options.cyclic, options.log_tau
    P, Q = tri_p.maps[b], tri_q.maps[b]
    vp, vq = vp[tri_p.offsets[b]:tri_p.offsets[b + 1]], vq[tri_q.offsets[b]:tri_q.offsets[b + 1]]
    cp, cq = np.take(P, vp, axis=0), np.take(Q, vq, axis=0)  # np.take: several times faster than P[vp]
    cand = candidate_pairs(cp, cq, sigma, log_tau, SPARSE_NEIGHBOURS)
    cost, shift = min_cost(cp, cq, cyclic, pairs=(cand[:, 0], cand[:, 1]))
    score = log_lr_from_cost(cost, sigma)
    if options.solve_lp:
        chosen = assign_sparse(score, cand, (len(vp), len(vq)), objective)
        # Both sorted by p index: map the chosen pairs back to their candidate rows.
        at = np.searchsorted(cand[:, 0] * len(vq) + cand[:, 1], chosen[:, 0] * len(vq) + chosen[:, 1])
        return chosen[:, 0], chosen[:, 1], score[at], shift[at]
    keep = score >= log_tau  # every candidate that can be declared
    return cand[keep, 0], cand[keep, 1], score[keep], shift[keep]
