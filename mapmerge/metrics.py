"""Ground-truth labels, detection counts, ROC curves and map-level errors.

A tentative triangle pair is *true* when its two triangles hold the same three
landmark ids (in any order); it is *order-consistent* when the Groth orders
agree vertex by vertex. Over the LP's tentative pairs at threshold τ:

- TP: true and declared;  FP: false and declared;
- MD: true and not declared (the paper's missed detections);  TN: the rest;
- ``common``: triangles with the same id set in both Delaunay graphs;
- ``unpaired``: common triangles the LP did not pair with their true partner.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
from scipy.special import chdtri

from .alignment import Alignment, align_pairs, covariance_in_p_frame, rotate, wrap_angle
from .combining import ONLY_Q, CombinedBatch
from .result import MergeResult


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
    ids_p, ids_q = np.asarray(ids_p)[None], np.asarray(ids_q)[None]
    return triangle_labels_batch(ids_p, ids_q, np.zeros(len(triangle_pairs), np.intp),
                                 vertices_p[triangle_pairs[:, 0]], vertices_q[triangle_pairs[:, 1]])


def triangle_labels_batch(ids_p, ids_q, trial, vertices_p, vertices_q):
    """``triangle_labels`` of the tentative pairs of B map pairs.

    Parameters
    ----------
    ids_p, ids_q : (B, n_p), (B, n_q) int ndarray
    trial : (M,) int ndarray
        Map pair of each tentative pair.
    vertices_p, vertices_q : (M, 3) int ndarray
        Groth-ordered landmarks of each pair's two triangles.
    """
    a = ids_p[trial[:, None], vertices_p]
    b = ids_q[trial[:, None], vertices_q]
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


def common_triangle_counts(ids_p, ids_q, tri_p, tri_q) -> np.ndarray:
    """Per map pair, the number of ``common_triangles`` (B,), from two ``TriangleBatch``."""
    n_ids = np.int64(_n_ids(ids_p, ids_q))

    def keys(ids, tri):
        s = np.sort(ids[tri.trial[:, None], tri.vertices], axis=1).astype(np.int64)
        return ((tri.trial * n_ids + s[:, 0]) * n_ids + s[:, 1]) * n_ids + s[:, 2]

    both = np.intersect1d(keys(ids_p, tri_p), keys(ids_q, tri_q), assume_unique=True)
    return np.bincount(both // n_ids**3, minlength=len(ids_p))


def detection_counts(is_true, declared, n_common: int) -> dict:
    """TP, FP, MD, TN over tentative pairs, plus ``common`` and ``unpaired``."""
    out = detection_counts_batch(np.zeros(len(np.ravel(is_true)), np.intp), is_true, declared,
                                 np.array([n_common]))
    return {k: int(v[0]) for k, v in out.items()}


def detection_counts_batch(trial, is_true, declared, n_common) -> dict:
    """``detection_counts`` per map pair: (B,) arrays, ``n_common`` (B,) the common triangles."""
    is_true = np.asarray(is_true, dtype=bool)
    declared = np.asarray(declared, dtype=bool)
    B = len(n_common)

    def per_trial(mask):
        return np.bincount(trial[mask], minlength=B)

    tp, md = per_trial(is_true & declared), per_trial(is_true & ~declared)
    return {"tp": tp, "fp": per_trial(~is_true & declared), "md": md, "tn": per_trial(~is_true & ~declared),
            "common": np.asarray(n_common), "unpaired": n_common - tp - md}


def oracle_log_tau(is_true, scores) -> float:
    """The paper's Fig. 1 rule: the smallest log τ with zero false positives.

    Uses ground truth (an oracle, not a usable threshold). With ``declared =
    score >= log τ`` it is the next float above the best false pair's score,
    or ``-inf`` when there is no false pair.
    """
    scores = np.asarray(scores, dtype=float)
    return float(oracle_log_tau_batch(np.zeros(scores.size, np.intp), is_true, scores, 1)[0])


def oracle_log_tau_batch(trial, is_true, scores, n_trials: int) -> np.ndarray:
    """``oracle_log_tau`` of each of ``n_trials`` map pairs (the oracle rule, per pair)."""
    is_true = np.asarray(is_true, dtype=bool)
    best_false = np.full(n_trials, -np.inf)
    np.maximum.at(best_false, trial[~is_true], scores[~is_true])
    return np.where(np.isneginf(best_false), -np.inf, np.nextafter(best_false, np.inf))


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
        If the inputs differ in length, a label is not boolean (or 0/1) or
        a score is NaN or ``+inf`` (``-inf`` is allowed).
    """
    y_true = np.asarray(y_true).ravel()
    if y_true.dtype != bool:
        if not np.all(np.isin(y_true, (0, 1))):
            raise ValueError(f"y_true must hold booleans or 0/1 labels, got values {np.unique(y_true)[:5].tolist()}")
        y_true = y_true.astype(bool)
    y_score = np.asarray(y_score, dtype=float).ravel()
    if y_true.shape != y_score.shape:
        raise ValueError(f"y_true and y_score must have the same length, got {y_true.size} and {y_score.size}")
    if np.any(np.isnan(y_score)) or np.any(y_score == np.inf):
        raise ValueError("y_score must not contain NaN or +inf")
    # Any sort order will do (ties move together below), so the fastest one.
    order = np.argsort(-y_score)
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
    """Area under a curve by the trapezoid rule (ROC: ``auc(fpr, tpr)``); NaN with under two points.

    Raises
    ------
    ValueError
        If the arrays are not 1-D of one length, or ``fpr`` decreases somewhere (a curve out of
        order has no area; ``roc_curve`` returns its points in order).
    """
    fpr, tpr = np.asarray(fpr, dtype=float), np.asarray(tpr, dtype=float)
    if fpr.ndim != 1 or fpr.shape != tpr.shape:
        raise ValueError(f"fpr and tpr must be 1-D and of the same length, got shapes {fpr.shape} and {tpr.shape}")
    if fpr.size < 2 or np.any(np.isnan(fpr)) or np.any(np.isnan(tpr)):
        return float("nan")
    if np.any(np.diff(fpr) < 0):
        raise ValueError("fpr must be non-decreasing (the points in roc_curve's order)")
    return float(np.trapezoid(tpr, fpr))


#: A merge succeeds when it matched, its rotation error is below this many
#: degrees and the combined map's RMSE below ``SUCCESS_RMSE_SIGMAS`` σ.
SUCCESS_DEG = 1.0
SUCCESS_RMSE_SIGMAS = 2.0
#: The transform is found when it matched, its rotation error is below
#: ``SUCCESS_DEG`` and the RMS per-coordinate registration error over the
#: common landmarks (estimated vs true transform applied to p's estimates of
#: them) is at most this many σ; landmark association is not part of it.
FOUND_RMS_SIGMAS = 1.0


def map_errors(scenario, result) -> dict:
    """Map-level errors of one merge against the scenario's ground truth.

    Parameters
    ----------
    scenario : Scenario or AgentPair
        Ground truth (``ids_p``, ``ids_q``, ``truth``, ``theta``, ``t``,
        ``sigma``, ``n_common``).
    result : MergeResult

    Returns
    -------
    dict
        ``matched``, ``n_pairs``, ``correct_pairs``, ``wrong_pairs``,
        ``missed_pairs`` (common landmarks not paired), ``n_conflicts``,
        ``rot_err_deg``, ``trans_err``, ``rmse`` (combined map vs truth in
        p's frame), ``duplicates`` (q-only rows of landmarks map p holds),
        ``success`` (see ``SUCCESS_DEG``), ``transform_found`` (see
        ``FOUND_RMS_SIGMAS``) and ``false_merge`` (matched maps that share
        no landmark); NaN errors when there is no match.
    """
    if not isinstance(result, MergeResult):
        raise ValueError(f"result must be the MergeResult of merge_maps, got {type(result).__name__}")
    c = result.combined
    origin = np.select([c.origin == "fused", c.origin == "p"], [0, 1], 2)
    # A batch of one of each, with the fields map_errors_batch reads.
    truth = SimpleNamespace(p=np.asarray(scenario.p)[None], ids_p=np.asarray(scenario.ids_p)[None],
                            ids_q=np.asarray(scenario.ids_q)[None], truth=np.asarray(scenario.truth)[None],
                            theta=np.array([scenario.theta]), t=np.asarray(scenario.t)[None],
                            sigma=np.array([scenario.sigma]), n_common=np.array([scenario.n_common]))
    rows = CombinedBatch(trial=np.zeros(len(c.points), np.intp), offsets=np.array([0, len(c.points)]),
                         points=c.points, origin=origin, index_p=c.index_p, index_q=c.index_q)
    merged = SimpleNamespace(pair_trial=np.zeros(len(result.pairs), np.intp), pairs=result.pairs,
                             n_conflicts=np.array([result.n_conflicts]), matched=np.array([result.matched]),
                             theta=np.array([result.theta]), t=np.asarray(result.t)[None], combined=rows)
    return {k: v[0].item() for k, v in map_errors_batch(truth, merged).items()}


def map_errors_batch(scenarios, merged) -> dict:
    """``map_errors`` of B merges at once: a dict of (B,) arrays.

    ``scenarios`` holds the ground truth with a leading batch axis
    (``simulate.ScenarioBatch``); ``merged`` is a ``MergeBatch``.
    """
    P, ids_p, ids_q, truth, sigma, n_common = (scenarios.p, scenarios.ids_p, scenarios.ids_q, scenarios.truth,
                                               scenarios.sigma, scenarios.n_common)
    true_theta, true_t = scenarios.theta, scenarios.t
    pair_trial, pairs, matched, theta, t = merged.pair_trial, merged.pairs, merged.matched, merged.theta, merged.t
    c = merged.combined
    row_trial, points, origin, index_p, index_q = c.trial, c.points, c.origin, c.index_p, c.index_q
    B = len(ids_p)
    K = np.bincount(pair_trial, minlength=B)
    correct = np.bincount(pair_trial, ids_p[pair_trial, pairs[:, 0]] == ids_q[pair_trial, pairs[:, 1]],
                          B).astype(np.int64)
    row_ids = np.where(index_p >= 0, ids_p[row_trial, index_p], ids_q[row_trial, index_q])
    sq_err = np.bincount(row_trial, np.sum((points - truth[row_trial, row_ids]) ** 2, axis=1), B)
    rmse = np.sqrt(sq_err / np.bincount(row_trial, minlength=B))
    rot_err_deg = np.degrees(np.abs(wrap_angle(theta - true_theta)))
    trans_err = np.sqrt(np.sum((t - true_t) ** 2, axis=1))
    # q-only rows of a landmark map p also holds.
    n_ids = np.int64(max(ids_p.max(), ids_q.max())) + 1
    in_p = np.isin(row_trial * n_ids + row_ids, np.arange(B)[:, None] * n_ids + ids_p)
    duplicates = np.bincount(row_trial, (origin == ONLY_Q) & in_p, B).astype(np.int64)
    trial_base = np.arange(B)[:, None] * n_ids
    registration = registration_rms(P, np.isin(trial_base + ids_p, trial_base + ids_q), theta, t, true_theta, true_t)
    nan = np.where(matched, 0.0, np.nan)
    return {
        "matched": matched, "n_pairs": K, "correct_pairs": correct, "wrong_pairs": K - correct,
        "missed_pairs": n_common - correct, "n_conflicts": np.asarray(merged.n_conflicts, dtype=np.int64),
        "rot_err_deg": rot_err_deg + nan, "trans_err": trans_err + nan, "rmse": rmse + nan,
        "duplicates": duplicates,
        "success": matched & (rot_err_deg < SUCCESS_DEG) & (rmse < SUCCESS_RMSE_SIGMAS * sigma),
        "transform_found": matched & _found(rot_err_deg, registration, sigma),
        "false_merge": matched & (n_common == 0),
    }


def registration_rms(P, common, theta, t, true_theta, true_t) -> np.ndarray:
    """RMS per-coordinate distance between the estimated and the true transform
    applied to the same points: p's estimates of its common landmarks.

    Parameters
    ----------
    P : (B, n, 2) ndarray
    common : (B, n) bool ndarray
        Rows of p whose landmark q also holds.
    theta, true_theta : (B,) ndarray
    t, true_t : (B, 2) ndarray

    Returns
    -------
    (B,) ndarray
        NaN where there is no common landmark or no estimate.
    """
    d = rotate(theta, P) + np.asarray(t)[:, None] - rotate(true_theta, P) - np.asarray(true_t)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.sum(common * np.sum(d**2, axis=2), axis=1) / (2 * np.sum(common, axis=1)))


def transform_found(scenario, theta: float, t) -> bool:
    """Whether a transform estimate of one map pair counts as found (see ``FOUND_RMS_SIGMAS``)."""
    rot_err = np.degrees(np.abs(wrap_angle(theta - scenario.theta)))
    common = np.isin(scenario.ids_p, scenario.ids_q)[None]
    rms = registration_rms(np.asarray(scenario.p)[None], common, np.array([theta]), np.asarray(t, float)[None],
                           np.array([scenario.theta]), np.asarray(scenario.t)[None])[0]
    return bool(_found(rot_err, rms, scenario.sigma))


def _found(rot_err_deg, registration, sigma):
    """The transform-found rule (``FOUND_RMS_SIGMAS``), shared by the batch and the one-pair form."""
    return (rot_err_deg < SUCCESS_DEG) & (registration <= FOUND_RMS_SIGMAS * sigma)


def correspondence_oracle_transform(scenario) -> Alignment:
    """The transform fitted by an oracle that knows every correspondence.

    The common landmarks, paired by their true ids, give the closed-form ML
    (θ*, t*) of n paired points (``alignment.align``). A matcher must also
    find the correspondences, which at low SNR even an association knowing
    the true transform cannot, so this is the reference for the transform's
    accuracy: with Gaussian noise it is efficient (its covariance is the
    Cramér-Rao bound ``Alignment.cov`` with the correspondences known).
    Labelled an oracle: it uses ground truth.

    Parameters
    ----------
    scenario : Scenario or AgentPair
        Ground truth (``p``, ``q``, ``ids_p``, ``ids_q``, ``sigma``).

    Returns
    -------
    Alignment

    Raises
    ------
    ValueError
        When the maps share fewer than 2 landmarks.
    """
    _, ip, iq = np.intersect1d(scenario.ids_p, scenario.ids_q, return_indices=True)
    if ip.size < 2:
        raise ValueError(f"scenario must share at least 2 landmarks, got {ip.size}")
    return align_pairs(np.asarray(scenario.p, float)[ip], np.asarray(scenario.q, float)[iq], float(scenario.sigma))


def oracle_association(P, Q, theta, t, cov_p, cov_q, density_q: float, p_shared: float):
    """The best landmark association any matcher could make: an oracle that knows the true transform.

    Given the TRUE (θ, t), each candidate pair (i, j) scores its posterior
    log-odds against "unshared":

        s_ij = log N(e_ij; 0, C_ij) - log λ_q + log(π / (1 - π)),

    ``e_ij = p_i - R(θ)ᵀ (q_j - t)``, ``C_ij = Σp_i + R(θ)ᵀ Σq_j R(θ)`` (both
    maps' noise, q's brought into p's frame), λ_q the landmark density of q
    (an unshared q landmark is anywhere) and π the prior that a landmark is
    shared. Leaving a landmark unshared scores 0. The association maximises
    the total score over one-to-one pairings (an assignment on each
    connected component of the positively scored pairs). Labelled an oracle:
    it uses ground truth.

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
    theta, t : float, (2,) ndarray
        The true transform, ``q ≈ R(θ) p + t``.
    cov_p, cov_q : (n_p, 2, 2), (n_q, 2, 2) ndarray
    density_q : float
        Landmarks of q per unit area, > 0.
    p_shared : float
        Prior probability that a landmark is shared, in (0, 1).

    Returns
    -------
    (K, 2) int ndarray
        Pairs (p index, q index), sorted by p index.
    """
    from .association import posterior_association

    if not density_q > 0 or not 0 < p_shared < 1:
        raise ValueError("density_q must be > 0 and p_shared in (0, 1)")
    x = rotate(-theta, np.asarray(Q, float) - t)
    log_prior = np.log(p_shared / (1 - p_shared)) - np.log(density_q)
    return posterior_association(np.asarray(P, float), x, cov_p, covariance_in_p_frame(theta, cov_q), log_prior,
                                 with_margin=False)[0]


@dataclasses.dataclass(frozen=True)
class KnownTransform:
    """A transform known exactly: ``q ≈ R(θ) p + t`` with a zero (θ, t) covariance."""

    theta: float
    t: np.ndarray
    cov: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((3, 3)))


def transform_oracle_association(P, Q, theta, t, sigma: float, cov_p=None, cov_q=None):
    """``consensus``'s own landmark association, given the TRUE transform and nothing else.

    ``oracle_association`` also knows the landmark density and the true
    prior π that a landmark is shared; this oracle estimates π from the maps
    exactly as ``association.associate`` does, so the gap between a matcher and
    it is what the matcher's transform error costs, and the gap between the
    two oracles is what not knowing π costs. Labelled an oracle: it uses
    ground truth.

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
    theta, t : float, (2,) ndarray
        The true transform, ``q ≈ R(θ) p + t``.
    sigma : float
    cov_p, cov_q : (n, 2, 2) ndarray, optional
        Per-landmark covariances (σ² I when not given).

    Returns
    -------
    (K, 2) int ndarray
        Pairs (p index, q index), sorted by p index.
    """
    from .association import associate

    known = KnownTransform(float(theta), np.asarray(t, dtype=float))
    return associate(np.asarray(P, float), np.asarray(Q, float), known, float(sigma), cov_p, cov_q,
                     with_margin=False)[0]


def oracle_pairs_batch(scenarios) -> dict:
    """Correct and wrong pairs of the two oracle associations of each of B simulated map pairs.

    ``oracle_association`` uses the scenarios' true transforms, covariances
    and association prior (``density``, ``p_shared`` within
    ``association.SHARED_RANGE``): the best any matcher could do.
    ``transform_oracle_association`` knows only the true transform.
    Labelled oracles: they use ground truth.

    Returns
    -------
    dict
        ``oracle_correct_pairs``, ``oracle_wrong_pairs``,
        ``transform_oracle_correct_pairs``, ``transform_oracle_wrong_pairs``:
        (B,) int arrays.
    """
    B = len(scenarios)
    counts = {key: np.zeros(B, np.int64) for key in ("oracle_correct_pairs", "oracle_wrong_pairs",
                                                     "transform_oracle_correct_pairs", "transform_oracle_wrong_pairs")}
    from .association import SHARED_RANGE

    # The prior is one number for every landmark, also those outside the
    # overlap, where none is shared: kept within the range consensus allows
    # its own estimate, so that "unshared" always has a price.
    p_shared = float(np.clip(scenarios.p_shared, *SHARED_RANGE))
    for b in range(B):  # one global assignment per map pair
        P, Q, theta, t = scenarios.p[b], scenarios.q[b], scenarios.theta[b], scenarios.t[b]
        cov_p, cov_q = scenarios.cov_p[b], scenarios.cov_q[b]
        for name, pairs in (
                ("oracle", oracle_association(P, Q, theta, t, cov_p, cov_q, scenarios.density, p_shared)),
                ("transform_oracle", transform_oracle_association(P, Q, theta, t, scenarios.sigma[b], cov_p, cov_q))):
            ok = scenarios.ids_p[b, pairs[:, 0]] == scenarios.ids_q[b, pairs[:, 1]]
            counts[f"{name}_correct_pairs"][b], counts[f"{name}_wrong_pairs"][b] = ok.sum(), (~ok).sum()
    return counts


def group_errors(team, group) -> dict:
    """Errors of a many-map merge (``merge_many``) against the team's ground truth.

    A placed map is placed *correctly* when its frame's rotation is within
    ``SUCCESS_DEG`` of the truth and the RMS distance between its landmarks
    (their true positions) carried into the reference frame by the
    estimated and by the true frame is within ``FOUND_RMS_SIGMAS`` σ (the
    pairwise "transform found" rule); any placement of a stranger, or of
    anything in the frame of a stranger, is *wrong*.

    Parameters
    ----------
    team : Team or any object with its attributes
        ``maps``, ``ids`` (true landmark id of each row), ``truth`` (true
        positions by id in a world frame; NaN rows are not scored),
        ``theta``, ``t`` (each map's frame, ``maps[i] ≈ R(θ_i) world + t_i``),
        ``sigma`` (one, or one per map) and ``stranger``.
    group : GroupMerge

    Returns
    -------
    dict
        ``placed_correct``, ``placed_wrong``, ``unplaced`` (team maps left
        out) and ``strangers_placed`` (counts); ``all_correct`` (every team
        map placed correctly and no stranger placed); ``status`` (per map:
        "correct", "wrong", "unplaced"), ``rot_err_deg`` and ``registration``
        (per map, NaN unplaced); ``nees`` (per map: the frame error's squared
        Mahalanobis length under ``frame_cov``, χ²₃ when the covariance is
        right) and ``beyond_cov`` (placed team maps whose ``nees`` exceeds
        the χ²₃ bound of tail probability 1e-3); ``track_purity`` (multi-map tracks holding
        one true landmark), ``track_completeness`` (landmarks seen by two or
        more placed team maps whose sightings are all in one track),
        ``duplicates`` (extra tracks of landmarks split over several),
        ``fused_rmse`` (all tracks) and ``shared_rmse`` (multi-map tracks)
        against the truth in the reference frame.
    """
    stranger = np.asarray(team.stranger, dtype=bool)
    truth = _reference_truth(team, int(group.reference))
    status, rot_err, registration, nees = _placements(team, group, stranger, truth)
    team_map = ~stranger
    return {
        "placed_correct": int(np.sum((status == "correct") & team_map)),
        "placed_wrong": int(np.sum(status == "wrong")),
        "unplaced": int(np.sum((status == "unplaced") & team_map)),
        "strangers_placed": int(np.sum(group.placed & stranger & (group.placed.sum() > 1))),
        "all_correct": bool(np.all(status[team_map] == "correct") and not np.any(status == "wrong")),
        "status": list(status), "rot_err_deg": rot_err, "registration": registration, "nees": nees,
        "beyond_cov": int(np.sum(nees > chdtri(3, 1e-3))),
        **_track_scores(team, group, team_map, truth[2]),
    }


def _reference_truth(team, ref: int):
    """The true frames relative to map ``ref`` and the map from the world into ``ref``'s frame."""
    # map i ≈ R(θ_i - θ_r) x_ref + t_i - R(θ_i - θ_r) t_r.
    N = len(team.maps)
    theta = np.asarray(team.theta, dtype=float) - team.theta[ref]
    t = np.asarray(team.t, dtype=float) - rotate(theta, np.broadcast_to(team.t[ref], (N, 1, 2)))[:, 0]
    return theta, t, lambda x: rotate(team.theta[ref], x) + team.t[ref]


def _placements(team, group, stranger, reference_truth):
    """Per map: "correct" / "wrong" / "unplaced", rotation error (deg), RMS registration and NEES."""
    N, ref = len(team.maps), int(group.reference)
    sigma = np.broadcast_to(np.asarray(team.sigma, dtype=float), (N,))
    true_theta, true_t, world_to_ref = reference_truth
    truth = np.asarray(team.truth, dtype=float)
    rot_err, registration, nees = np.full(N, np.nan), np.full(N, np.nan), np.full(N, np.nan)
    status = np.where(group.placed, "wrong", "unplaced").astype(object)
    for i in np.flatnonzero(group.placed):
        if stranger[i] or stranger[ref]:
            continue
        x = world_to_ref(truth[team.ids[i]])
        x = x[~np.isnan(x[:, 0])]
        d = rotate(group.theta[i], x) + group.t[i] - rotate(true_theta[i], x) - true_t[i]
        rot_err[i] = np.degrees(np.abs(wrap_angle(group.theta[i] - true_theta[i])))
        registration[i] = np.sqrt(np.mean(np.sum(d**2, axis=1)) / 2)
        if i != ref:
            e = np.concatenate([[wrap_angle(group.theta[i] - true_theta[i])], group.t[i] - true_t[i]])
            nees[i] = e @ np.linalg.solve(group.frame_cov[i], e)
        if _found(rot_err[i], registration[i], sigma[i]):
            status[i] = "correct"
    if stranger[ref] and group.placed.sum() == 1:
        status[ref] = "unplaced"  # a stranger alone in its own frame placed nothing
    return status, rot_err, registration, nees


def _track_scores(team, group, team_map, world_to_ref) -> dict:
    """Track purity, completeness, duplicates and the fused map's RMSE (``group_errors``)."""
    tracks = group.tracks
    present = tracks >= 0
    ids = np.full(tracks.shape, -1)
    for i in range(len(team.maps)):
        ids[present[:, i], i] = np.asarray(team.ids[i])[tracks[present[:, i], i]]
    multi = present.sum(axis=1) >= 2
    first = ids[np.arange(len(ids)), np.argmax(present, axis=1)]
    pure = np.all((ids == first[:, None]) | ~present, axis=1)
    # Each (track, true id) once, over the tracks holding a team map's landmark.
    team_tracks = np.any(present & team_map, axis=1)
    k, i = np.nonzero(present & team_tracks[:, None])
    _, per_id = np.unique(np.unique(np.stack([ids[k, i], k], axis=1), axis=0)[:, 0], return_counts=True)
    in_tracks = np.unique(ids[k, i])
    # Completeness: landmarks sighted by two or more placed team maps, all their sightings in one track.
    sighted = [np.asarray(team.ids[m]) for m in np.flatnonzero(group.placed & team_map)]
    seen, count = np.unique(np.concatenate(sighted + [np.zeros(0, np.intp)]), return_counts=True)
    shared = seen[count >= 2]
    one_track = np.isin(shared, in_tracks[per_id == 1])
    truth = np.asarray(team.truth, dtype=float)
    scored = pure & team_tracks & ~np.isnan(truth[first, 0])
    err2 = np.sum((group.merged - world_to_ref(truth[first])) ** 2, axis=1)
    with np.errstate(invalid="ignore"):
        return {
            "track_purity": float(np.mean(pure[multi])) if multi.any() else np.nan,
            "track_completeness": float(np.mean(one_track)) if shared.size else np.nan,
            "duplicates": int(np.sum(per_id - 1)),
            "fused_rmse": float(np.sqrt(np.mean(err2[scored]) / 2)) if scored.any() else np.nan,
            "shared_rmse": float(np.sqrt(np.mean(err2[scored & multi]) / 2)) if (scored & multi).any() else np.nan,
        }
