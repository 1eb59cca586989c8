"""Groth (1986)'s star-pattern matcher on the Delaunay triangles.

Groth used every triple of the brightest stars; Delaunay keeps it linear.
Each triangle gets the rotation/translation/scale invariants R = r3/r2
(longest over shortest side) and C = cos of the angle at vertex 1, with
Groth's tolerances for a vertex position error ε; pairs whose invariants
agree within the tolerances and whose orientation agrees are matched, every
match votes for its three vertex correspondences, the correspondences with
at least two votes are accepted one-to-one in decreasing vote order, and the
transform is fitted with the n-point closed form, dropping the worst
correspondence outside a χ²₂ gate and refitting until none is left outside
(Groth's iterative rejection).
"""

from __future__ import annotations

import numpy as np

from ..alignment import paired_transforms, reject_outliers
from ..matching import correspondences
from ..result import MergeBatch, build_from_parts
from ..triangles import TriangleBatch

#: Groth's ε, the position tolerance of a vertex, in units of σ.
GROTH_EPS_SIGMAS = 3.0
#: Groth's limit on the side ratio R: longer triangles are too unstable.
GROTH_MAX_RATIO = 10.0
#: Outlier gate on the fitted correspondences (χ²₂ tail probability).
GROTH_GATE_P = 1e-3


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


def groth_pairs(P, Q, sigma, tri_p, tri_q):
    """Groth's matching on one map pair.

    Returns
    -------
    tri_pairs : (M, 2) int ndarray
        Triangle pairs whose invariants agree.
    scores : (M,) ndarray
        Their GLRT log Λ (reported, not used).
    declared : (M,) bool ndarray
        Pairs all of whose vertex correspondences were accepted.
    pairs : (K, 2) int ndarray
        Accepted landmark correspondences.
    n_conflicts : int
    """
    eps = GROTH_EPS_SIGMAS * sigma
    Rp, Cp, tRp, tCp, sp = _invariants(tri_p.coords, eps)
    Rq, Cq, tRq, tCq, sq = _invariants(tri_q.coords, eps)
    ok = (
        ((Rp[:, None] - Rq[None]) ** 2 < tRp[:, None] + tRq[None])
        & ((Cp[:, None] - Cq[None]) ** 2 < tCp[:, None] + tCq[None])
        & (sp[:, None] == sq[None])
        & (Rp[:, None] < GROTH_MAX_RATIO)
        & (Rq[None] < GROTH_MAX_RATIO)
    )
    tri_pairs = np.argwhere(ok).astype(np.intp)
    vp, vq = tri_p.vertices[tri_pairs[:, 0]], tri_q.vertices[tri_pairs[:, 1]]
    _, _, cost = paired_transforms(P[vp], Q[vq])
    pairs, n_conflicts = _vote(vp, vq)
    pairs = reject_outliers(P, Q, pairs, sigma, GROTH_GATE_P)
    to_q = np.full(P.shape[0], -1)
    to_q[pairs[:, 0]] = pairs[:, 1]
    return tri_pairs, -cost / (2 * sigma**2), np.all(to_q[vp] == vq, axis=1), pairs, n_conflicts


def _vote(vp, vq):
    """One-to-one correspondences by decreasing votes, at least two votes each."""
    pairs, conflicts = correspondences(vp, vq, np.ones(len(vp)))
    if pairs.shape[0] == 0:
        return pairs, conflicts
    n = int(max(vp.max(), vq.max())) + 1
    keys, votes = np.unique(vp.ravel() * n + vq.ravel(), return_counts=True)
    v = votes[np.searchsorted(keys, pairs[:, 0] * n + pairs[:, 1])]
    return pairs[v >= 2], conflicts


def merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, rng=None) -> MergeBatch:
    """Groth's matcher on B map pairs (``rng`` unused: the method is deterministic)."""
    parts = [groth_pairs(P[b], Q[b], float(sigma[b]), tri_p[b], tri_q[b]) for b in range(len(P))]
    return build_from_parts(method="groth", P=P, Q=Q, sigma=sigma, log_tau=np.full(len(P), np.nan),
                            tri_p=tri_p, tri_q=tri_q, parts=parts)
