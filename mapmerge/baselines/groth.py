"""Groth (1986)'s star-pattern matcher on the Delaunay triangles.

Groth used every triple of the brightest stars; Delaunay keeps it linear.
Each triangle gets the rotation/translation/scale invariants R = r3/r2
(longest over shortest side) and C = cos of the angle at vertex 1, with
Groth's tolerances for a vertex position error ε; pairs whose invariants
agree within the tolerances and whose orientation agrees are matched, every
match votes for its three vertex correspondences, the correspondences with
at least two votes are accepted one-to-one in decreasing vote order (equal
votes: the one whose best voter's invariants agree most closely first, so
that the landmarks' order in the maps does not matter), and the
transform is fitted with the n-point closed form, dropping the worst
correspondence outside a χ²₂ gate and refitting until none is left outside
(Groth's iterative rejection). Every step runs on a whole batch of map
pairs at once, each pair's result the same as alone.
"""

from __future__ import annotations

import numpy as np

from ..alignment import reject_outliers_batch
from ..correspondence import resolve_correspondences
from ..result import MergeBatch, build_batch
from ..statistic import BLOCK_PAIRS, min_cost
from ..triangles import TriangleBatch

#: Groth's ε, the position tolerance of a vertex, in units of σ.
GROTH_EPS_SIGMAS = 3.0
#: Groth's limit on the side ratio R: longer triangles are too unstable.
GROTH_MAX_RATIO = 10.0
#: Outlier gate on the fitted correspondences (χ²₂ tail probability).
GROTH_GATE_P = 1e-3
#: Triangle pairs passing the invariant test of one map pair beyond which the
#: method refuses (a ValueError) rather than exhaust memory: every passing pair
#: votes and is kept, at about 480 bytes each (so about 10 GB at the limit).
#: The count grows like n² (at 30 dB 3.7·10⁵ at 1,000 landmarks per map,
#: 4.9·10⁶ at 3,000 (2.4 GB), 6.5·10⁷ at 10⁴: the limit is reached near
#: 6,000 landmarks per map).
GROTH_MAX_PAIRS = 2 * 10**7


def _invariants(coords, eps):
    v1, v2, v3 = coords[:, 0], coords[:, 1], coords[:, 2]
    a, b = v2 - v1, v3 - v1
    r2 = np.linalg.norm(a, axis=1)  # shortest side, v1-v2
    r3 = np.linalg.norm(b, axis=1)  # longest side, v3-v1
    R = r3 / r2
    C = np.sum(a * b, axis=1) / (r2 * r3)
    F = eps**2 * (1 / r3**2 - C / (r3 * r2) + 1 / r2**2)
    tR2 = 2 * R**2 * F
    tC2 = 2 * (1 - C**2) * F + 3 * C**2 * F**2
    sense = np.sign(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    return R, C, tR2, tC2, sense


def groth_pairs(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch):
    """Groth's matching on B map pairs at once.

    Returns
    -------
    tri_trial : (M,) int ndarray
        Map pair of each triangle pair, sorted.
    tri_pairs : (M, 2) int ndarray
        Triangle pairs whose invariants agree (indices within each map).
    scores : (M,) ndarray
        Their GLRT log Λ (reported, not used).
    declared : (M,) bool ndarray
        Pairs all of whose vertex correspondences were accepted.
    pair_trial, pairs : (K,), (K, 2) int ndarray
        Accepted landmark correspondences, sorted by map pair.
    n_conflicts : (B,) int ndarray
    """
    B = len(P)
    eps = GROTH_EPS_SIGMAS * sigma
    coords_p, coords_q = tri_p.coords(), tri_q.coords()
    Rp, Cp, tRp, tCp, sp = _invariants(coords_p, eps[tri_p.trial])
    Rq, Cq, tRq, tCq, sq = _invariants(coords_q, eps[tri_q.trial])
    tri_trial, i, j = _agreeing_triangles(tri_p, tri_q, (Rp, Cp, tRp, tCp, sp), (Rq, Cq, tRq, tCq, sq))
    tri_pairs = np.stack([i, j], axis=1)
    gp, gq = tri_p.offsets[tri_trial] + i, tri_q.offsets[tri_trial] + j
    vp, vq = tri_p.vertices[gp], tri_q.vertices[gq]
    cost = min_cost(coords_p, coords_q, pairs=(gp, gq))[0]  # the GLRT's, in Groth order
    # How closely each pair's invariants agree, in units of their tolerances (larger is closer): it breaks
    # ties in votes, which the landmarks' order would otherwise break.
    agreement = -((Rp[gp] - Rq[gq]) ** 2 / (tRp[gp] + tRq[gq]) + (Cp[gp] - Cq[gq]) ** 2 / (tCp[gp] + tCq[gq]))
    pair_trial, pairs, n_conflicts = _vote(tri_trial, vp, vq, agreement, max(P.shape[1], Q.shape[1]), B)
    keep = reject_outliers_batch(P, Q, pair_trial, pairs, sigma, GROTH_GATE_P)
    pair_trial, pairs = pair_trial[keep], pairs[keep]
    to_q = np.full(B * P.shape[1], -1)
    to_q[pair_trial * P.shape[1] + pairs[:, 0]] = pairs[:, 1]
    partner = to_q[(tri_trial * P.shape[1])[:, None] + vp] == vq
    declared = partner[:, 0] & partner[:, 1] & partner[:, 2]
    return tri_trial, tri_pairs, -cost / (2 * sigma[tri_trial] ** 2), declared, pair_trial, pairs, n_conflicts


def _agreeing_triangles(tri_p: TriangleBatch, tri_q: TriangleBatch, inv_p: tuple, inv_q: tuple):
    """The triangle pairs of each map pair whose invariants (``_invariants`` of p's and q's triangles)
    agree: their map pair, p triangle and q triangle (within its map), in row-major order."""
    Rp, Cp, tRp, tCp, sp = inv_p
    Rq, Cq, tRq, tCq, sq = inv_q
    B = len(tri_p)
    # Every p triangle against every q triangle of its own map pair, a block of map pairs at a time;
    # a large map pair alone, a slice of its p triangles at a time (row-major order either way).
    tp, tq = int(tri_p.count.max(initial=0)), int(tri_q.count.max(initial=0))
    block = max(1, BLOCK_PAIRS // max(tp * tq, 1))
    rows_per = tp if tp * tq <= BLOCK_PAIRS else max(1, 16 * BLOCK_PAIRS // tq)
    found = []
    for a in range(0, B, block):
        maps = np.arange(a, min(a + block, B))
        all_rows, cols = _padded_rows(tri_p, maps, tp), _padded_rows(tri_q, maps, tq)
        n_found = 0
        for r in range(0, max(tp, 1), rows_per):
            rows = all_rows[:, r:r + rows_per]
            Rr, Cr, tRr, tCr, sr = (x[rows][:, :, None] for x in (Rp, Cp, tRp, tCp, sp))
            Rc, Cc, tRc, tCc, sc = (x[cols][:, None, :] for x in (Rq, Cq, tRq, tCq, sq))
            ok = (
                (rows[:, :, None] >= 0) & (cols[:, None, :] >= 0)
                & ((Rr - Rc) ** 2 < tRr + tRc) & ((Cr - Cc) ** 2 < tCr + tCc) & (sr == sc)
                & (Rr < GROTH_MAX_RATIO) & (Rc < GROTH_MAX_RATIO)
            )
            k, i, j = np.nonzero(ok)
            found.append((maps[k], r + i, j))
            n_found += len(k)
            if n_found > GROTH_MAX_PAIRS * len(maps):
                raise ValueError(f"method 'groth': over {GROTH_MAX_PAIRS:,} triangle pairs of one map pair "
                                 f"({tp:,} x {tq:,} triangles) pass its invariant test and all would vote "
                                 "(about 480 bytes each); Groth's matcher is for small maps: use method='consensus'")
    tri_trial, i, j = (np.concatenate(v).astype(np.intp) for v in zip(*found))
    return tri_trial, i, j


def _padded_rows(tri: TriangleBatch, maps: np.ndarray, width: int) -> np.ndarray:
    """Rows of ``tri`` of each of ``maps`` as (len(maps), width), -1 past a map's own triangles."""
    slot = np.arange(width)
    return np.where(slot < tri.count[maps][:, None], tri.offsets[maps][:, None] + slot, -1)


def _vote(tri_trial, vp, vq, agreement, n, B):
    """One-to-one correspondences by decreasing votes, at least two votes each, per map pair, equal votes
    ranked by the closest invariant agreement among their voters (landmark indices offset by ``n`` per map
    pair, so that one call serves them all)."""
    off = (tri_trial * n)[:, None]
    uniq, keep, votes = resolve_correspondences(off + vp, off + vq, agreement, min_votes=2)
    winners = np.flatnonzero(keep)
    return ((uniq[winners, 0] // n).astype(np.intp), (uniq[winners] % n).astype(np.intp),
            np.bincount(uniq[~keep & (votes >= 2), 0] // n, minlength=B))


def merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, rng=None) -> MergeBatch:
    """Groth's matcher on B map pairs (``rng`` unused: the method is deterministic)."""
    tri_trial, tri_pairs, scores, declared, pair_trial, pairs, n_conflicts = groth_pairs(P, Q, sigma, tri_p, tri_q)
    return build_batch(method="groth", P=P, Q=Q, sigma=sigma, log_tau=np.full(len(P), np.nan), tri_p=tri_p,
                       tri_q=tri_q, tri_trial=tri_trial, triangle_pairs=tri_pairs, triangle_log_lr=scores,
                       declared=declared, pair_trial=pair_trial, pairs=pairs, n_conflicts=n_conflicts)
