"""Bipartite matching of triangles (paper eq. 14), the τ test, correspondences.

``match_triangles`` is the triangle-matching driver: triangulate a batch of
map pairs, score their triangle pairs with the GLRT and solve each pair's
LP. Only the Delaunay calls and the LP run per map pair.

The LP (14) has an integral optimum, so it is solved as an assignment
problem with ``scipy.optimize.linear_sum_assignment``. A rectangular score
matrix is the LP with ``N = max(Np, Nq)`` padded by zero-score dummies: the
surplus triangles stay unmatched. On large maps the LP over the gated
candidate pairs is a min-cost flow (``assign_sparse``, OR-Tools), which
solves it in seconds at 10⁵ landmarks per map where scipy's sparse
assignment (LAPJVsp) took minutes.

The paper maximises Σ Λ (``objective="lr"``). Maximising Σ log Λ
(``objective="loglr"``) is the other natural reading; with a forced full
assignment it lets hopeless pairs' huge negative scores push true pairs out,
which the harness measures.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, reverse_cuthill_mckee
from scipy.spatial import cKDTree
from scipy.special import chdtri

from .statistic import log_lr_from_cost, min_cost, pairwise_log_lr_blocks
from .triangles import PARALLEL_MIN_LANDMARKS, TriangleBatch, triangulate_batches

OBJECTIVES = ("lr", "loglr")

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


def assign(log_lr: np.ndarray, objective: str = "lr") -> np.ndarray:
    """Tentative triangle pairs from the assignment LP (14).

    Parameters
    ----------
    log_lr : (Tp, Tq) ndarray
        Pairwise log Λ.
    objective : {"lr", "loglr"}
        Maximise Σ Λ (the paper) or Σ log Λ.

    Returns
    -------
    (min(Tp, Tq), 2) int ndarray
        Rows ``(i, j)``: triangle i of p tentatively paired with j of q,
        sorted by i.
    """
    rows, cols = linear_sum_assignment(lp_weight(log_lr, check_objective(objective)), maximize=True)
    return np.stack([rows, cols], axis=1).astype(np.intp)


def check_objective(objective: str) -> str:
    """``objective`` if it is one of ``OBJECTIVES``, else a one-line ValueError."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    return objective


def lp_weight(log_lr: np.ndarray, objective: str) -> np.ndarray:
    """What the LP maximises the sum of: Λ (``"lr"``) or log Λ (``"loglr"``)."""
    # Λ = exp(log Λ) underflows to 0 for hopeless pairs: they are then exact
    # ties at zero weight, which is what Σ Λ means for them.
    return np.exp(log_lr) if objective == "lr" else log_lr


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
    workers = -1 if len(coords_p) >= 2 * PARALLEL_MIN_LANDMARKS else 1  # a map has about 2n triangles
    dist, idx = tree.query(side_features(coords_p), k=k, distance_upper_bound=gate_radius(sigma, log_tau),
                           workers=workers)
    dist, idx = dist.reshape(len(coords_p), k), idx.reshape(len(coords_p), k)
    # Sorted within each row (neighbours the gate left out last): rows come in order, so pairs are by (p, q).
    idx = np.where(np.isfinite(dist), idx, len(coords_q))
    idx.sort(axis=1)
    rows, slot = np.nonzero(idx < len(coords_q))
    return np.stack([rows, idx[rows, slot]], axis=1).astype(np.intp)


#: Integer cost resolution of the sparse LP: gains are scaled so that the
#: largest is ``2**SPARSE_COST_BITS`` (OR-Tools' min-cost flow is exact on
#: integers), or less where cost times node count would overflow its 64-bit
#: arithmetic (40 bits at 10⁵ landmarks per map). A float64 sum of Λ + 1,
#: the weights of an assignment solver, resolves 52.
SPARSE_COST_BITS = 52


def assign_sparse(log_lr: np.ndarray, pairs: np.ndarray, shape, objective: str = "lr") -> np.ndarray:
    """The LP (14) restricted to candidate pairs, every p triangle free to stay unpaired.

    A min-cost flow (OR-Tools' ``SimpleMinCostFlow``, cost scaling): one
    unit from each p triangle, through a candidate pair to its q triangle
    or straight to the sink (unpaired), at cost minus the pair's gain
    (Λ for ``"lr"``; log Λ above the smallest candidate's for ``"loglr"``,
    where staying unpaired is worth the smallest). Gains are rounded to
    integers ``2**-SPARSE_COST_BITS`` of the largest apart (fewer bits on
    graphs too large for that), so that pairs whose gains differ by less
    may tie, and a pair whose gain rounds to 0 stays unpaired: at 10⁵
    landmarks per map, Λ below about 2⁻⁴⁰ (log Λ < -27.7).

    Returns
    -------
    (M, 2) int ndarray
        Tentative pairs among ``pairs``, sorted by p index.

    Raises
    ------
    RuntimeError
        If the flow solver fails (it does not on these graphs).
    ImportError
        Without OR-Tools (the extra ``[large]``).
    """
    try:
        from ortools.graph.python import min_cost_flow  # imported here: only large maps take this path
    except ImportError:
        raise ImportError("the LP of large maps (a min-cost flow) needs OR-Tools: "
                          "pip install 'mapmerge[large]'") from None

    check_objective(objective)
    n_p, n_q = shape
    if pairs.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    gain = np.exp(log_lr) if objective == "lr" else log_lr - float(log_lr.min())
    # Nodes: p triangles 0..n_p-1, q triangles n_p..n_p+n_q-1, source, sink.
    source, sink = n_p + n_q, n_p + n_q + 1
    # OR-Tools refuses costs beyond about 2**61.6 / (node count); two bits spare.
    bits = min(SPARSE_COST_BITS, 59 - int(np.ceil(np.log2(sink + 2))))
    top = float(gain.max())
    cost = -np.rint(gain * (2.0**bits / top if top > 0 else 0.0)).astype(np.int64)
    # A pair whose gain rounds to 0 is worth no more than leaving its p triangle unpaired: dropping it
    # leaves the optimum's value (such pairs lie far below any usual τ: log Λ < -27.7 at 10⁵ landmarks).
    worth = cost < 0
    pairs, cost = pairs[worth], cost[worth]
    p_node, q_node = local_numbering(pairs, n_p, n_q)
    flow = min_cost_flow.SimpleMinCostFlow()
    flow.add_arcs_with_capacity_and_unit_cost(
        np.concatenate([np.full(n_p, source), p_node[pairs[:, 0]], np.arange(n_p), n_p + np.arange(n_q)]),
        np.concatenate([np.arange(n_p), q_node[pairs[:, 1]], np.full(n_p, sink), np.full(n_q, sink)]),
        np.ones(n_p + len(pairs) + n_p + n_q, dtype=np.int64),
        np.concatenate([np.zeros(n_p, np.int64), cost, np.zeros(n_p + n_q, np.int64)]))
    supplies = np.zeros(sink + 1, dtype=np.int64)
    supplies[source], supplies[sink] = n_p, -n_p
    flow.set_nodes_supplies(np.arange(sink + 1), supplies)
    status = flow.solve()
    if status != flow.OPTIMAL:
        raise RuntimeError(f"the sparse LP's min-cost flow failed: {status}")
    chosen = pairs[flow.flows(np.arange(n_p, n_p + len(pairs))) > 0]
    return chosen[np.argsort(chosen[:, 0], kind="stable")].astype(np.intp)


def local_numbering(pairs: np.ndarray, n_p: int, n_q: int) -> tuple[np.ndarray, np.ndarray]:
    """Flow-graph node numbers of the p triangles (0..n_p-1) and q triangles (n_p..) that keep neighbours close.

    Triangles come in Delaunay's order, scattered over the map, so the candidate pairs of one p triangle
    point at q nodes far apart in memory. Numbered along a reverse Cuthill-McKee order of the candidate
    graph (p and q triangles each in their order of it), OR-Tools' min-cost flow solves the same LP
    faster (measurements: docs/tuning.md). Exactly tied optima may resolve differently.
    """
    n = n_p + n_q
    ends = np.concatenate([pairs[:, 0], n_p + pairs[:, 1]])
    graph = csr_matrix((np.ones(len(ends), np.int8), (ends, np.roll(ends, len(pairs)))), shape=(n, n))
    order = reverse_cuthill_mckee(graph, symmetric_mode=True)
    is_p = order < n_p
    p_node, q_node = np.empty(n_p, np.intp), np.empty(n_q, np.intp)
    p_node[order[is_p]] = np.arange(n_p)
    q_node[order[~is_p] - n_p] = n_p + np.arange(n_q)
    return p_node, q_node


#: Label-spreading sweeps ``candidate_components`` tries before it hands a
#: long chain of contested pairs to scipy's connected components.
LABEL_SWEEPS = 6


def candidate_components(i: np.ndarray, j: np.ndarray, n_p: int, n_q: int) -> np.ndarray:
    """Connected component of each candidate pair (i, j) in the bipartite graph of all candidates.

    An assignment over the candidates decomposes into one small assignment
    per component (``component_blocks``).
    """
    # Contests are mostly a few pairs: spreading the smallest pair index over shared
    # landmarks settles them in a few sweeps, far cheaper than a sparse graph.
    label = np.arange(i.size)
    for _ in range(LABEL_SWEEPS):
        low_p, low_q = np.full(n_p, i.size), np.full(n_q, i.size)
        np.minimum.at(low_p, i, label)
        np.minimum.at(low_q, j, label)
        spread = np.minimum(low_p[i], low_q[j])
        if np.array_equal(spread, label):
            return label
        label = spread
    graph = coo_matrix((np.ones(i.size), (i, n_p + j)), shape=(n_p + n_q,) * 2)
    _, label = connected_components(graph, directed=False)
    return label[i]


def component_blocks(i: np.ndarray, j: np.ndarray, values: np.ndarray, component: np.ndarray, fill: float):
    """Each component's candidates as a dense block: yields ``(rows, cols, block)``.

    ``block[r, c]`` is the value of the candidate (rows[r], cols[c]) and
    ``fill`` where the pair is not a candidate.
    """
    if not component.size:
        return
    # Every component's rows and columns ranked at once (one sort each, not two np.unique per
    # component: most components are two or three pairs, where the per-call overhead is the cost).
    rows, row_of, row_start = _ranks_within(component, i)
    cols, col_of, col_start = _ranks_within(component, j)
    order = np.argsort(component, kind="stable")
    start = [0, *(np.flatnonzero(np.diff(component[order])) + 1).tolist(), component.size]
    ri, ci, v = row_of[order], col_of[order], values[order]
    row_start, col_start = row_start.tolist(), col_start.tolist()
    for k in range(len(start) - 1):
        a, b = start[k], start[k + 1]
        r, c = rows[row_start[k]:row_start[k + 1]], cols[col_start[k]:col_start[k + 1]]
        block = np.full((r.size, c.size), fill)
        block[ri[a:b], ci[a:b]] = v[a:b]
        yield r, c, block


def _ranks_within(group: np.ndarray, x: np.ndarray):
    """The distinct x of each group, ascending, groups in ascending order; each element's rank among
    its group's; and where each group's distinct values start (one more entry at the end)."""
    order = np.lexsort((x, group))
    g, v = group[order], x[order]
    first, new = np.ones(g.size, bool), np.ones(g.size, bool)
    np.not_equal(g[1:], g[:-1], out=first[1:])
    np.not_equal(v[1:], v[:-1], out=new[1:])
    new |= first
    distinct = np.cumsum(new) - 1  # each element's index among all distinct (group, x)
    start = distinct[first]
    rank = np.empty_like(distinct)
    rank[order] = distinct - start[np.cumsum(first) - 1]
    return v[new], rank, np.append(start, distinct[-1] + 1)


def correspondences(vertices_p, vertices_q, log_lr):
    """One-to-one landmark correspondences implied by declared triangle pairs.

    Each declared pair gives three correspondences, vertex i to vertex i.
    When a landmark ends up paired with two different partners, the
    correspondence supported by more declared triangles wins, then the one
    with the higher best triangle log Λ, then the lower indices; the losers
    are dropped and counted.

    Parameters
    ----------
    vertices_p, vertices_q : (M, 3) int ndarray
        Landmark indices of the declared pairs' triangles, row m of
        ``vertices_p`` paired vertex by vertex with row m of ``vertices_q``.
    log_lr : (M,) ndarray
        Their scores.

    Returns
    -------
    pairs : (K, 2) int ndarray
        Landmark index pairs (p, q), sorted by p index.
    n_conflicts : int
        Distinct candidate correspondences dropped as conflicting.
    """
    uniq, keep, _ = resolve_correspondences(vertices_p, vertices_q, log_lr)
    return uniq[keep].astype(np.intp), int(keep.size - np.count_nonzero(keep))


def resolve_correspondences(vertices_p, vertices_q, log_lr=None, min_votes=1):
    """Candidate correspondences of declared pairs and which of them survive.

    The rule of ``correspondences``, returned in full so that callers
    holding many independent map pairs (landmark indices offset per pair)
    can count conflicts per pair. Without ``log_lr``, votes alone rank
    (then the lower indices). Candidates with fewer than ``min_votes`` votes
    take no part: they neither survive nor block another (as if ranked after
    every other, whose fate they cannot change).

    Returns
    -------
    uniq : (U, 2) int64 ndarray
        Distinct candidate correspondences (p, q), sorted by (p, q).
    keep : (U,) bool ndarray
        The one-to-one survivors.
    votes : (U,) int64 ndarray
        How many declared pairs' vertices gave each candidate.
    """
    if len(vertices_p) == 0:
        return np.empty((0, 2), dtype=np.int64), np.empty(0, dtype=bool), np.empty(0, dtype=np.int64)
    vp, vq = np.ravel(vertices_p).astype(np.int64, copy=False), np.ravel(vertices_q).astype(np.int64, copy=False)
    # Keyed by (p, q - p), which orders as (p, q) and spans a small range when both indices carry
    # the same per-map-pair offset.
    d = vq - vp
    lo = int(d.min())
    width = int(d.max()) - lo + 1
    keys = vp * width + (d - lo)
    score = None if log_lr is None else np.repeat(log_lr, 3)
    # Only each group's size and best score are read, so the order within a group is free: count the
    # keys in a table where their range is small, sort them where it is not (large maps).
    n_keys = (int(vp.max()) + 1) * width
    if n_keys <= KEY_TABLE_FACTOR * keys.size:
        counts = np.bincount(keys, minlength=n_keys)
        present = np.flatnonzero(counts)
        all_votes = counts[present]
        if score is not None:
            best = np.full(n_keys, -np.inf)
            np.maximum.at(best, keys, score)
            best = best[present]
    else:
        order = np.argsort(keys)
        keys = keys[order]
        start = np.flatnonzero(np.concatenate(([True], keys[1:] != keys[:-1])))
        present = keys[start]
        all_votes = np.diff(np.concatenate((start, [keys.size])))
        if score is not None:
            best = np.maximum.reduceat(score[order], start)
    p, d = np.divmod(present, width)
    uniq = np.stack([p, p + d + lo], axis=1)  # sorted by (p, q), as the keys
    # Only candidates sharing a landmark with another can lose; rank those.
    keep = all_votes >= min_votes
    up, uq = uniq[keep, 0], uniq[keep, 1]
    contested = np.flatnonzero(keep)[(np.bincount(up)[up] > 1) | (np.bincount(uq)[uq] > 1)]
    if contested.size == 0:
        return uniq, keep, all_votes
    cp, cq = uniq[contested, 0], uniq[contested, 1]
    # Rank: votes down, then the best score down, then position ((p, q) order). By votes alone a key
    # ordering as (votes down, position) serves without a sort; with scores, the score is compared
    # among each landmark's leaders by votes (``_leaders``) rather than sorted: many candidates (Groth's
    # hundreds per map pair) and few rounds.
    votes = all_votes[contested]
    rank = (votes.max() - votes) * contested.size + np.arange(contested.size)
    best = None if score is None else best[contested]
    # Greedy in rank order, in rounds: a candidate ranked first among the
    # live ones sharing its p and its q is exactly one the sequential greedy
    # keeps; keeping it kills its rivals. Conflicts are rare, so few rounds.
    won = np.zeros(contested.size, dtype=bool)
    taken_p, taken_q = np.zeros(int(cp.max()) + 1, dtype=bool), np.zeros(int(cq.max()) + 1, dtype=bool)
    live = np.arange(contested.size)  # shrinks each round: most candidates die in the first ones
    while live.size:
        lp, lq, lr = cp[live], cq[live], rank[live]
        lb = None if best is None else best[live]
        first = _leaders(lp, lr, votes[live], lb) & _leaders(lq, lr, votes[live], lb)
        won[live[first]] = True
        taken_p[lp[first]] = taken_q[lq[first]] = True
        live = live[~taken_p[lp] & ~taken_q[lq]]
    keep[contested] = won
    return uniq, keep, all_votes


_NO_RANK = np.iinfo(np.int64).max
#: ``resolve_correspondences`` counts candidates in a table when the range of
#: their (p, q) keys is at most this many times their number, else sorts them.
KEY_TABLE_FACTOR = 8


def _leaders(landmark: np.ndarray, rank: np.ndarray, votes: np.ndarray, score: np.ndarray | None) -> np.ndarray:
    """Whether each candidate comes first among the candidates of its landmark: by ``rank`` (votes down,
    then position) or, with ``score``, the most votes, then the best score, then position."""
    top = np.full(int(landmark.max()) + 1, _NO_RANK)
    if score is None:
        np.minimum.at(top, landmark, rank)
        return rank == top[landmark]
    most = np.zeros(len(top), dtype=votes.dtype)
    np.maximum.at(most, landmark, votes)
    lead = votes == most[landmark]
    high = np.full(len(top), -np.inf)
    np.maximum.at(high, landmark[lead], score[lead])
    lead &= score == high[landmark]
    np.minimum.at(top, landmark[lead], rank[lead])
    return lead & (rank == top[landmark])


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
        parts = [_sparse_pairs(tri_p, tri_q, vp, vq, b, float(sigma[b]), objective, cyclic, log_tau, solve_lp)
                 for b in range(len(tri_p))]
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


def _sparse_pairs(tri_p, tri_q, vp, vq, b, sigma, objective, cyclic, log_tau, solve_lp):
    """(i, j, log Λ, shift) of the tentative pairs of map pair ``b`` on the gated sparse graph."""
    P, Q = tri_p.maps[b], tri_q.maps[b]
    vp, vq = vp[tri_p.offsets[b]:tri_p.offsets[b + 1]], vq[tri_q.offsets[b]:tri_q.offsets[b + 1]]
    cand = candidate_pairs(P[vp], Q[vq], sigma, log_tau, SPARSE_NEIGHBOURS)
    cost, shift = min_cost(P[vp], Q[vq], cyclic, pairs=(cand[:, 0], cand[:, 1]))
    score = log_lr_from_cost(cost, sigma)
    if solve_lp:
        chosen = assign_sparse(score, cand, (len(vp), len(vq)), objective)
        # Both sorted by p index: map the chosen pairs back to their candidate rows.
        at = np.searchsorted(cand[:, 0] * len(vq) + cand[:, 1], chosen[:, 0] * len(vq) + chosen[:, 1])
        return chosen[:, 0], chosen[:, 1], score[at], shift[at]
    keep = score >= log_tau  # every candidate that can be declared
    return cand[keep, 0], cand[keep, 1], score[keep], shift[keep]
