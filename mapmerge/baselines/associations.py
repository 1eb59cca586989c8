"""Shared pieces of the outside peers (CPD, CLIPPER, TEASER++): putative associations, acceptance, and a
random generator per map pair for those that draw (CLIPPER, astroalign).

Acceptance: none of the peers has a test of its own, so each accepts a
merge when its inlier count reaches a bound per map size (``min_inliers``),
set on unrelated pairs at 30 dB with seeds disjoint from the reported ones
(``python -m experiments.peers --calibrate``: 1,000 pairs per size; the
bound lets at most one of them through).

CLIPPER and TEASER++ take putative correspondences. Landmarks carry no
descriptor, so every landmark of p is associated with every landmark of q
(all-to-all, as both methods' authors do without descriptors) while the
product n_p·n_q is at most ``ALL_TO_ALL_MAX``. Beyond it (CLIPPER's affinity
matrix is dense, (n_p·n_q)² entries) each landmark of p is associated with
the ``GATE_K`` landmarks of q whose rotation-invariant signatures (the
sorted distances to their ``SIGNATURE_NEIGHBOURS`` nearest neighbours in
their own map) are closest: a gating of ours, not the authors'.
"""

from __future__ import annotations

import hashlib

import numpy as np
from scipy.spatial import cKDTree

from ..result import MIN_MATCHED_LANDMARKS, MergeBatch, build_from_parts

#: Largest n_p·n_q for all-to-all associations (2,500: 50 x 50 landmarks; 50 MB of CLIPPER affinity).
ALL_TO_ALL_MAX = 2500
#: Candidates of q kept per landmark of p past ``ALL_TO_ALL_MAX``.
GATE_K = 10
#: Nearest neighbours in a landmark's own map that make up its signature.
SIGNATURE_NEIGHBOURS = 3


def rotate_about_centroid(X: np.ndarray, angle: float) -> np.ndarray:
    """The points ``X`` (n, 2) rotated by ``angle`` about their centroid."""
    c, s = np.cos(angle), np.sin(angle)
    mean = X.mean(axis=0)
    return (X - mean) @ np.array([[c, s], [-s, c]]) + mean


def pair_generators(P, Q, rng=None) -> list[np.random.Generator]:
    """A generator for each of the B map pairs (P, Q: (B, n, 2)): ``rng`` (seed or Generator), one shared
    by the batch, or without it one per pair seeded by its two maps' bytes, so that the same maps give the
    same draws in any batch and on any worker."""
    if rng is not None:
        return [np.random.default_rng(rng)] * len(P)
    return [np.random.default_rng(np.frombuffer(hashlib.sha256(p.tobytes() + q.tobytes()).digest(), dtype=np.uint32))
            for p, q in zip(P, Q)]


def merge_by_inliers(method: str, inliers, bounds: dict[int, int], P, Q, sigma, tri_p, tri_q,
                     gens=None) -> MergeBatch:
    """A peer's merge of B map pairs: ``inliers(P_b, Q_b, sigma_b)`` gives its one-to-one inlier set,
    accepted when it holds at least ``min_inliers(bounds, ...)`` (and ``MIN_MATCHED_LANDMARKS``) pairs,
    else no pair (an honest "no match"); the transform is ``build_batch``'s closed-form fit on it.
    ``gens``: a peer that draws gets each pair's generator (``pair_generators``) as a fourth argument."""
    empty = (np.empty((0, 2), dtype=np.intp), np.empty(0), np.empty(0, bool))
    need = max(MIN_MATCHED_LANDMARKS, min_inliers(bounds, P.shape[1], Q.shape[1]))
    parts = []
    for b in range(len(P)):
        pairs = inliers(P[b], Q[b], float(sigma[b]), *(() if gens is None else (gens[b],)))
        parts.append((*empty, pairs if len(pairs) >= need else np.empty((0, 2), dtype=np.intp), 0))
    return build_from_parts(method=method, P=P, Q=Q, sigma=sigma, log_tau=np.full(len(P), np.nan),
                            tri_p=tri_p, tri_q=tri_q, parts=parts)


def putative_associations(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Putative correspondences (A, 2) of landmarks of p and q: all-to-all, or gated past ``ALL_TO_ALL_MAX``."""
    n_p, n_q = len(P), len(Q)
    if n_p * n_q <= ALL_TO_ALL_MAX:
        i, j = np.meshgrid(np.arange(n_p), np.arange(n_q), indexing="ij")
        return np.stack([i.ravel(), j.ravel()], axis=1).astype(np.intp)
    k = min(SIGNATURE_NEIGHBOURS, n_p - 1, n_q - 1)
    sig_p, sig_q = (cKDTree(X).query(X, k + 1)[0][:, 1:] for X in (P, Q))
    nearest = cKDTree(sig_q).query(sig_p, min(GATE_K, n_q))[1].reshape(n_p, -1)
    return np.stack([np.repeat(np.arange(n_p), nearest.shape[1]), nearest.ravel()], axis=1).astype(np.intp)


def one_to_one(pairs: np.ndarray) -> np.ndarray:
    """The first pair of every landmark of either map (in the given order), sorted by p's index."""
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    keep = np.zeros(len(pairs), bool)
    keep[np.unique(pairs[:, 0], return_index=True)[1]] = True
    first_q = np.zeros(len(pairs), bool)
    first_q[np.unique(pairs[:, 1], return_index=True)[1]] = True
    pairs = pairs[keep & first_q]
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def min_inliers(table: dict[int, int], n_p: int, n_q: int) -> int:
    """The acceptance bound on a peer's inlier count for maps of n_p and n_q landmarks.

    ``table`` maps calibrated map sizes to the least inlier count accepted there. Chance inliers grow
    with the map size, so the bound of the smallest calibrated size at least min(n_p, n_q) is used
    (the largest size's beyond it).
    """
    n = min(n_p, n_q)
    sizes = sorted(table)
    return table[next((k for k in sizes if k >= n), sizes[-1])]
