"""Ground-truth labels, detection counts, ROC curves and map-level errors (DESIGN §4).

A tentative triangle pair is *true* when its two triangles hold the same three
landmark ids (in any order); it is *order-consistent* when the Groth orders
agree vertex by vertex. Over the LP's tentative pairs at threshold τ:

- TP: true and declared;  FP: false and declared;
- MD: true and not declared (the paper's missed detections);  TN: the rest;
- ``common``: triangles with the same id set in both Delaunay graphs;
- ``unpaired``: common triangles the LP did not pair with their true partner.
"""

from __future__ import annotations

import numpy as np

from .statistic import wrap_angle


def _sorted_id_keys(ids: np.ndarray, vertices: np.ndarray, n_ids: int) -> np.ndarray:
    """One int64 per triangle identifying its (unordered) landmark-id set."""
    tri_ids = np.sort(ids[vertices], axis=1).astype(np.int64)
    return (tri_ids[:, 0] * n_ids + tri_ids[:, 1]) * n_ids + tri_ids[:, 2]


def _n_ids(ids_p, ids_q) -> int:
    return int(max(ids_p.max(), ids_q.max())) + 1


def triangle_labels(ids_p, ids_q, vertices_p, vertices_q, triangle_pairs):
    """Truth of tentative triangle pairs.

    Parameters
    ----------
    ids_p, ids_q : (n_p,), (n_q,) int ndarray
        True landmark id of each map row.
    vertices_p, vertices_q : (Tp, 3), (Tq, 3) int ndarray
        Groth-ordered triangles.
    triangle_pairs : (M, 2) int ndarray

    Returns
    -------
    is_true : (M,) bool ndarray
        Same landmark-id set.
    order_consistent : (M,) bool ndarray
        Same ids vertex by vertex (implies ``is_true``).
    """
    ids_p, ids_q = np.asarray(ids_p), np.asarray(ids_q)
    a = ids_p[vertices_p[triangle_pairs[:, 0]]]
    b = ids_q[vertices_q[triangle_pairs[:, 1]]]
    is_true = np.all(np.sort(a, axis=1) == np.sort(b, axis=1), axis=1)
    return is_true, np.all(a == b, axis=1)


def common_triangles(ids_p, ids_q, vertices_p, vertices_q):
    """Triangles present with the same landmark-id set in both maps.

    Returns
    -------
    (C, 2) int ndarray
        Index pairs (triangle in p, triangle in q), sorted by p index.
    """
    ids_p, ids_q = np.asarray(ids_p), np.asarray(ids_q)
    n_ids = _n_ids(ids_p, ids_q)
    kp = _sorted_id_keys(ids_p, vertices_p, n_ids)
    kq = _sorted_id_keys(ids_q, vertices_q, n_ids)
    _, ip, iq = np.intersect1d(kp, kq, assume_unique=True, return_indices=True)
    order = np.argsort(ip)
    return np.stack([ip[order], iq[order]], axis=1)


def detection_counts(is_true, declared, n_common: int) -> dict:
    """TP, FP, MD, TN over tentative pairs, plus ``common`` and ``unpaired``."""
    is_true = np.asarray(is_true, dtype=bool)
    declared = np.asarray(declared, dtype=bool)
    tp = int(np.sum(is_true & declared))
    md = int(np.sum(is_true & ~declared))
    return {
        "tp": tp,
        "fp": int(np.sum(~is_true & declared)),
        "md": md,
        "tn": int(np.sum(~is_true & ~declared)),
        "common": int(n_common),
        "unpaired": int(n_common - tp - md),
    }


def oracle_log_tau(is_true, scores) -> float:
    """The paper's Fig. 1 rule: the smallest log τ with zero false positives.

    Uses ground truth (an oracle, not a usable threshold). With ``declared =
    score >= log τ`` it is the next float above the best false pair's score,
    or ``-inf`` when there is no false pair.
    """
    is_true = np.asarray(is_true, dtype=bool)
    false_scores = np.asarray(scores, dtype=float)[~is_true]
    if false_scores.size == 0:
        return -np.inf
    return float(np.nextafter(false_scores.max(), np.inf))


def roc_curve(y_true, y_score):
    """Receiver operating characteristic, in scikit-learn's convention.

    Parameters
    ----------
    y_true : (m,) array_like of bool
        Labels (True = pair of the same landmarks).
    y_score : (m,) array_like of float
        Scores; a pair is declared when ``score >= threshold``.

    Returns
    -------
    fpr, tpr : ndarray
        P_FA and P_D at each threshold, starting at (0, 0).
    thresholds : ndarray
        Decreasing; the first is ``+inf`` (declare nothing).

    Raises
    ------
    ValueError
        If the inputs differ in length or contain a non-finite score
        (``-inf`` is allowed).
    """
    y_true = np.asarray(y_true, dtype=bool).ravel()
    y_score = np.asarray(y_score, dtype=float).ravel()
    if y_true.shape != y_score.shape:
        raise ValueError(f"y_true and y_score must have the same length, got {y_true.size} and {y_score.size}")
    if np.any(np.isnan(y_score)) or np.any(y_score == np.inf):
        raise ValueError("y_score must not contain NaN or +inf")
    order = np.argsort(-y_score, kind="stable")
    score, label = y_score[order], y_true[order]
    # Keep the last index of every run of equal scores: ties move together.
    last = np.r_[np.flatnonzero(np.diff(score) != 0), score.size - 1] if score.size else np.array([], int)
    tps = np.cumsum(label)[last]
    fps = (last + 1) - tps
    n_pos, n_neg = int(label.sum()), int((~label).sum())
    tpr = np.r_[0.0, tps / n_pos] if n_pos else np.r_[0.0, np.full(last.size, np.nan)]
    fpr = np.r_[0.0, fps / n_neg] if n_neg else np.r_[0.0, np.full(last.size, np.nan)]
    return fpr, tpr, np.r_[np.inf, score[last]]


def auc(fpr, tpr) -> float:
    """Area under a curve by the trapezoid rule (ROC: ``auc(fpr, tpr)``)."""
    fpr, tpr = np.asarray(fpr, dtype=float), np.asarray(tpr, dtype=float)
    if fpr.size < 2 or np.any(np.isnan(fpr)) or np.any(np.isnan(tpr)):
        return float("nan")
    return float(np.trapezoid(tpr, fpr))


def map_errors(scenario, result, success_deg: float = 1.0, success_rmse_sigmas: float = 2.0) -> dict:
    """Map-level errors of one merge against the scenario's ground truth.

    Parameters
    ----------
    scenario : Scenario
        Ground truth (``ids_p``, ``ids_q``, ``truth``, ``theta``, ``t``, ``sigma``).
    result : MergeResult
    success_deg, success_rmse_sigmas : float
        A merge succeeds when it matched, its rotation error is below
        ``success_deg`` degrees and the combined map's RMSE is below
        ``success_rmse_sigmas · σ``.

    Returns
    -------
    dict
        ``matched``, ``rot_err_deg``, ``trans_err``, ``rmse`` (combined map vs
        truth in p's frame), ``n_pairs``, ``correct_pairs``, ``wrong_pairs``,
        ``missed_pairs`` (common landmarks not paired), ``duplicates`` (extra
        rows of one landmark in the combined map), ``n_conflicts``, ``success``.
    """
    ids_p, ids_q = scenario.ids_p, scenario.ids_q
    pairs = result.pairs
    correct = int(np.sum(ids_p[pairs[:, 0]] == ids_q[pairs[:, 1]])) if pairs.size else 0
    out = {
        "matched": bool(result.matched),
        "n_pairs": int(pairs.shape[0]),
        "correct_pairs": correct,
        "wrong_pairs": int(pairs.shape[0] - correct),
        "missed_pairs": int(scenario.n_common - correct),
        "n_conflicts": int(result.n_conflicts),
    }
    if not result.matched:
        out.update(rot_err_deg=np.nan, trans_err=np.nan, rmse=np.nan, duplicates=0, success=False)
        return out
    rot_err = abs(float(wrap_angle(result.theta - scenario.theta)))
    combined = result.combined
    row_ids = np.where(combined.index_p >= 0, ids_p[combined.index_p], ids_q[combined.index_q])
    err = combined.points - scenario.truth[row_ids]
    rmse = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    rot_err_deg = float(np.degrees(rot_err))
    out.update(
        rot_err_deg=rot_err_deg,
        trans_err=float(np.linalg.norm(result.t - scenario.t)),
        rmse=rmse,
        duplicates=int(row_ids.size - np.count_nonzero(np.bincount(row_ids))),
        success=bool(rot_err_deg < success_deg and rmse < success_rmse_sigmas * scenario.sigma),
    )
    return out
