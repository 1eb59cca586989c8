"""The assignment LP (paper eq. 14) and the components of a candidate graph.

The LP (14) has an integral optimum, so it is solved as an assignment
problem with ``scipy.optimize.linear_sum_assignment`` (``assign``). A
rectangular score matrix is the LP with ``N = max(Np, Nq)`` padded by
zero-score dummies: the surplus triangles stay unmatched. On large maps the
LP over the gated candidate pairs is a min-cost flow (``assign_sparse``,
OR-Tools), which solves it in seconds at 10⁵ landmarks per map where scipy's
sparse assignment (LAPJVsp) took minutes.

The paper maximises Σ Λ (``objective="lr"``). Maximising Σ log Λ
(``objective="loglr"``) is the other natural reading; with a forced full
assignment it lets hopeless pairs' huge negative scores push true pairs out,
which the harness measures.

An assignment over sparse candidates decomposes into one small assignment
per connected component of the candidate graph: ``candidate_components``
labels them and ``component_blocks`` hands out each one's dense block
(``mapmerge.association`` solves its landmark assignments so).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, reverse_cuthill_mckee

OBJECTIVES = ("lr", "loglr")



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
    sink = n_p + n_q + 1
    # OR-Tools refuses costs beyond about 2**61.6 / (node count); two bits spare.
    bits = min(SPARSE_COST_BITS, 59 - int(np.ceil(np.log2(sink + 2))))
    top = float(gain.max())
    cost = -np.rint(gain * (2.0**bits / top if top > 0 else 0.0)).astype(np.int64)
    # A pair whose gain rounds to 0 is worth no more than leaving its p triangle unpaired: dropping it
    # leaves the optimum's value (such pairs lie far below any usual τ: log Λ < -27.7 at 10⁵ landmarks).
    worth = cost < 0
    return _solve_flow(min_cost_flow.SimpleMinCostFlow(), pairs[worth], cost[worth], n_p, n_q)


def _solve_flow(flow, pairs: np.ndarray, cost: np.ndarray, n_p: int, n_q: int) -> np.ndarray:
    """The pairs ``assign_sparse``'s flow graph routes a unit through, sorted by p index.

    ``flow`` is an empty OR-Tools ``SimpleMinCostFlow``; ``cost`` the pairs' integer costs.
    """
    source, sink = n_p + n_q, n_p + n_q + 1
    p_node, q_node = local_numbering(pairs, n_p, n_q)
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

