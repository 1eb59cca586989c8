"""Landmark correspondences from declared triangle pairs, by vote.

Each declared triangle pair gives three correspondences, vertex i to vertex
i. ``correspondences`` keeps a one-to-one set of them: when a landmark is
claimed by two partners, the correspondence supported by more declared
triangles wins, then the one with the higher best log Λ, then the lower
indices. ``resolve_correspondences`` returns the whole vote, so that callers
holding many map pairs (landmark indices offset per pair) resolve them in
one call and count each pair's conflicts.
"""

from __future__ import annotations

import numpy as np

from .neighbours import njit


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
    present, all_votes, best = _grouped_keys(keys, score, (int(vp.max()) + 1) * width)
    p, d = np.divmod(present, width)
    uniq = np.stack([p, p + d + lo], axis=1)  # sorted by (p, q), as the keys
    # Only candidates sharing a landmark with another can lose; rank those.
    keep = all_votes >= min_votes
    up, uq = uniq[keep, 0], uniq[keep, 1]
    contested = np.flatnonzero(keep)[(np.bincount(up)[up] > 1) | (np.bincount(uq)[uq] > 1)]
    if contested.size == 0:
        return uniq, keep, all_votes
    cp, cq = uniq[contested, 0], uniq[contested, 1]
    # The sequential greedy in rank order: votes down, then the best score down, then position ((p, q)
    # order: lexsort is stable).
    votes = all_votes[contested]
    order = np.lexsort((-votes,) if score is None else (-best[contested], -votes))
    keep[contested] = _keep_in_order(cp, cq, order)
    return uniq, keep, all_votes


def _grouped_keys(keys, score, n_keys: int):
    """The distinct ``keys`` (ascending), how often each occurs and, with ``score``, each one's best score.

    Only each group's size and best score are read, so the order within a group is free: the keys are
    counted in a table where their range (``n_keys``) is small, sorted where it is not (large maps).
    """
    best = None
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
    return present, all_votes, best


@njit(cache=True)
def _keep_in_order(cp, cq, order):
    """The sequential greedy: in ``order``, each candidate whose p and q are both free is kept and takes them."""
    won = np.zeros(cp.size, dtype=np.bool_)
    taken_p, taken_q = np.zeros(cp.max() + 1, dtype=np.bool_), np.zeros(cq.max() + 1, dtype=np.bool_)
    for k in order:
        if not (taken_p[cp[k]] or taken_q[cq[k]]):
            won[k] = taken_p[cp[k]] = taken_q[cq[k]] = True
    return won


#: ``resolve_correspondences`` counts candidates in a table when the range of
#: their (p, q) keys is at most this many times their number, else sorts them.
KEY_TABLE_FACTOR = 8
