"""Match and merge stochastic landmark maps: the methods and the whole pipeline.

``merge_maps`` runs one method end to end on one map pair; ``merge_batch``
runs it on B map pairs at once, and ``merge_maps`` is its batch of one. For
the paper's method: triangulate both maps (Groth order), score every
triangle pair with the closed-form GLRT, solve the assignment LP (14),
declare the tentative pairs whose log Λ passes log τ, turn them into
one-to-one landmark correspondences, align with the n-point closed form and
build the combined map (15).

``METHODS`` is the one registry of methods, used by ``merge_maps`` and by
the Monte Carlo harness. A method has two stages so that callers comparing
thresholds on the same maps match once and declare per τ:
``match_stage`` (τ-independent: triangles and tentative pairs) and
``merge_at`` (declare at log τ, associate, combine: the registry entry's
own ``merge``, called with a ``MergeInputs``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import consensus, search
from ._validation import (check_covariances, check_finite, check_geometry, check_points, check_rng, check_sigma,
                          check_sigma_range, float_array)
from .alignment import rotation, wrap_angle
from .assignment import check_objective
from .baselines import astroalign as astroalign_baseline
from .baselines import clipper as clipper_baseline
from .baselines import cpd as cpd_baseline
from .baselines import groth as groth_baseline
from .baselines import teaser as teaser_baseline
from .correspondence import resolve_correspondences
from .matching import TriangleMatch, match_triangles, resolve_log_tau
from .result import MergeBatch, MergeResult, build_batch
from .triangles import triangulate_batches


@dataclass(frozen=True)
class MergeInputs:
    """What a method's ``merge`` takes: B valid map pairs and the results of the match stage.

    Attributes
    ----------
    method : str
        The method's name (what the ``MergeBatch`` reports).
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    sigma : (B,) ndarray
    match : TriangleMatch or None
        The tentative triangle pairs (``match_stage``); None for methods without τ.
    log_tau : (B,) ndarray
        The threshold of each map pair.
    cov_p, cov_q : (B, n, 2, 2) ndarray or None
        The landmarks' own covariances.
    rng : Generator or None
        Randomness of randomised baselines.
    search_memo : search.SearchMemo or None
        Global searches already made on these map pairs (consensus's fallback).
    """

    method: str
    P: np.ndarray
    Q: np.ndarray
    sigma: np.ndarray
    match: TriangleMatch | None
    log_tau: np.ndarray
    cov_p: np.ndarray | None = None
    cov_q: np.ndarray | None = None
    rng: np.random.Generator | None = None
    search_memo: object = None


def _declared_merge(x: MergeInputs) -> MergeBatch:
    """The triangle-LP methods (paper, cyclic): declare at log τ, resolve the correspondences, fit and combine."""
    match, P, Q = x.match, x.P, x.Q
    declared = match.log_lr >= x.log_tau[match.trial]
    # Landmark indices offset by pair so that one call resolves every pair's conflicts.
    n = max(P.shape[1], Q.shape[1])
    tb = match.trial[declared][:, None] * n
    uniq, keep, _ = resolve_correspondences(tb + match.p_vertices[declared], tb + match.q_vertices[declared],
                                         match.log_lr[declared])
    pairs = uniq[keep]
    return build_batch(
        method=x.method, P=P, Q=Q, sigma=x.sigma, log_tau=x.log_tau, tri_p=match.tri_p, tri_q=match.tri_q,
        tri_trial=match.trial, triangle_pairs=match.triangle_pairs, triangle_log_lr=match.log_lr,
        declared=declared, pair_trial=pairs[:, 0] // n, pairs=(pairs % n).astype(np.intp),
        n_conflicts=np.bincount(uniq[~keep, 0] // n, minlength=len(P)),
    )


def _consensus_merge(x: MergeInputs, statistic: str = "nfa") -> MergeBatch:
    """``consensus``: verification, association and acceptance by the triangle test's ``statistic``; the global
    search when triangles find nothing."""
    return consensus.consensus_merge(x.P, x.Q, x.sigma, x.match, x.log_tau, x.cov_p, x.cov_q,
                                     fallback=x.search_memo or search.search_batch, statistic=statistic)


def _search_merge(x: MergeInputs) -> MergeBatch:
    """``search``: the global (θ, t) search, no triangle matching."""
    return search.search_merge(x.P, x.Q, x.sigma, *triangulate_batches(x.P, x.Q), x.cov_p, x.cov_q)


def _baseline_merge(baseline: Callable, x: MergeInputs) -> MergeBatch:
    """A baseline's ``merge(P, Q, sigma, tri_p, tri_q, rng)`` on the map pairs."""
    return baseline(x.P, x.Q, x.sigma, *triangulate_batches(x.P, x.Q), x.rng)


@dataclass(frozen=True)
class Method:
    """A matcher variant.

    Attributes
    ----------
    name : str
    summary : str
        One line for listings.
    uses_tau : bool
        Whether the method declares triangle pairs by a threshold τ (the
        triangle-LP methods); the baselines have none.
    cyclic : bool
        Order-robust statistic (best orientation-preserving correspondence).
    solve_lp : bool
        Whether the sparse large-map path solves the LP (False: every gated
        candidate passing τ is kept, for consensus verification).
    merge : callable
        ``merge(MergeInputs) -> MergeBatch``: the method's τ-dependent stage
        (``merge_at``); by default the triangle-LP declaration of the paper.
    """

    name: str
    summary: str
    uses_tau: bool = True
    cyclic: bool = False
    solve_lp: bool = True
    merge: Callable[[MergeInputs], MergeBatch] = _declared_merge


#: The registry: every method ``merge_maps`` and the harness accept.
METHODS = {m.name: m for m in (
    Method("paper", "the seed paper: Groth order, GLRT, LP (14), τ, eq. (15)"),
    Method("cyclic", "the paper with the order-robust statistic (best cyclic vertex order)", cyclic=True),
    Method("consensus", "order-robust statistic + transform-consistent verification, landmark association "
           "and an a contrario acceptance test, the global search when triangles find nothing",
           cyclic=True, solve_lp=False, merge=_consensus_merge),
    Method("consensus_count", "consensus whose tests rank small maps' matches (up to 50 landmarks) by their "
           "association count: more found on 5-50 landmarks at the same false-merge rate (the default: use this)",
           cyclic=True, solve_lp=False, merge=functools.partial(_consensus_merge, statistic="count")),
    Method("search", "global (θ, t) search with an a contrario acceptance test, no triangles (low SNR)",
           uses_tau=False, merge=_search_merge),
    Method("groth", "baseline: Groth (1986) invariant triangle voting", uses_tau=False,
           merge=functools.partial(_baseline_merge, groth_baseline.merge)),
    Method("astroalign", "baseline: astroalign.find_transform (optional extra [baselines])", uses_tau=False,
           merge=functools.partial(_baseline_merge, astroalign_baseline.merge)),
    Method("cpd", "peer: rigid Coherent Point Drift (pycpd, optional extra [peers])", uses_tau=False,
           merge=functools.partial(_baseline_merge, cpd_baseline.merge)),
    Method("clipper", "peer: CLIPPER consistency graph (built by tools/build_peers.sh)", uses_tau=False,
           merge=functools.partial(_baseline_merge, clipper_baseline.merge)),
    Method("teaser", "peer: TEASER++ with z = 0 (built by tools/build_peers.sh)", uses_tau=False,
           merge=functools.partial(_baseline_merge, teaser_baseline.merge)),
)}

#: Default threshold: reject 1 % of true, order-consistent triangle pairs.
DEFAULT_TAU = "chi2:0.01"

#: Default method of ``merge_maps``, ``merge_batch``, ``merge_many`` and ``mapmerge merge``: ``consensus`` on
#: maps of more than 50 landmarks, and on smaller ones the test that finds more of them at the same rate.
DEFAULT_METHOD = "consensus_count"


def get_method(method) -> Method:
    """The registry entry of a method name, or a one-line ValueError."""
    try:
        return METHODS[method]
    except (KeyError, TypeError):
        raise ValueError(f"method must be one of {tuple(METHODS)}, got {method!r}") from None


def match_stage(P: np.ndarray, Q: np.ndarray, sigma: np.ndarray, method: str, objective: str = "lr",
                log_tau: float | None = None) -> TriangleMatch | None:
    """The τ-independent stage of a method on B map pairs (valid inputs).

    Returns the tentative triangle pairs of the triangle-LP methods, None
    for the baselines. ``log_tau`` is the loosest threshold that will be
    applied (it enables the sparse path on large maps).
    """
    m = get_method(method)
    if not m.uses_tau:
        return None
    return match_triangles(P, Q, sigma, objective, cyclic=m.cyclic, log_tau=log_tau, solve_lp=m.solve_lp)


def merge_at(P: np.ndarray, Q: np.ndarray, sigma: np.ndarray, match: TriangleMatch | None, log_tau: np.ndarray, *,
             method: str, cov_p=None, cov_q=None, rng=None, search_memo=None) -> MergeBatch:
    """Declare at log τ (one per map pair), associate landmarks and combine (valid inputs).

    ``cov_p``/``cov_q`` (B, n, 2, 2): the landmarks' own covariances, used by
    consensus's gates (their per-coordinate variance) and by the fusion of
    every method's combined map (information weighting). ``search_memo``
    (a ``search.SearchMemo``) lets calls on the same map pairs at other
    thresholds reuse consensus's global searches.
    """
    m = get_method(method)
    batch = m.merge(MergeInputs(m.name, P, Q, sigma, match, log_tau, cov_p, cov_q, rng, search_memo))
    return batch if cov_p is None else batch.with_covariances(cov_p, cov_q)


def merge_batch(P, Q, sigma, *, tau=DEFAULT_TAU, method=DEFAULT_METHOD, objective="lr", cov_p=None,
                cov_q=None, rng=None) -> MergeBatch:
    """``merge_maps`` on B map pairs of equal sizes at once.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
        The maps, each as ``merge_maps`` takes them (n >= 3 finite, distinct,
        not all collinear points).
    sigma : float or (B,) array_like
    tau, method, objective, rng
        As for ``merge_maps`` (one threshold for every pair).
    cov_p, cov_q : (B, n) or (B, n, 2, 2) array_like, optional
        Per-landmark variances or covariances of each map pair's maps.

    Returns
    -------
    MergeBatch
        ``.result(b)`` is pair b's ``MergeResult``.

    Raises
    ------
    ValueError
        On maps that are not (B, n, 2) arrays of valid maps (naming the bad
        one), a ``sigma`` or covariances not one per map pair, or any
        argument ``merge_maps`` would refuse.
    """
    P, Q = _check_batch(P, "P"), _check_batch(Q, "Q")
    if len(P) != len(Q):
        raise ValueError(f"P and Q must hold the same number of maps, got {len(P)} and {len(Q)}")
    sigma = float_array(sigma, f"sigma must be a real number or one per map pair, got {sigma!r}")
    if sigma.shape not in ((), (len(P),)):
        raise ValueError(f"sigma must be a number or one per map pair, shape ({len(P)},), got shape {sigma.shape}")
    sigma = np.broadcast_to(sigma, (len(P),)).copy()
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError("sigma must be positive and finite for every map pair")
    check_sigma_range(sigma)
    if (cov_p is None) != (cov_q is None):
        raise ValueError("cov_p and cov_q must be given together")
    cov_p, cov_q = (None if cov is None else _check_batch_covariances(cov, maps, name)
                    for cov, maps, name in ((cov_p, P, "cov_p"), (cov_q, Q, "cov_q")))
    return _merge(P, Q, sigma, (cov_p, cov_q), _Options(tau, method, objective, rng))


def _check_batch_covariances(cov, maps: np.ndarray, name: str) -> np.ndarray:
    cov = float_array(cov, f"{name} must be an array of real numbers")
    if cov.ndim not in (2, 4) or len(cov) != len(maps):
        raise ValueError(f"{name} must have shape (B, n) or (B, n, 2, 2) with B = {len(maps)} map pairs, "
                         f"got {cov.shape}")
    return np.stack([check_covariances(c, maps.shape[1], name) for c in cov])


def pooled_sigma(cov_p, cov_q) -> float:
    """One σ from per-landmark covariances: the RMS per-coordinate standard deviation over both maps.

    Parameters
    ----------
    cov_p, cov_q : (n, 2, 2) ndarray
        Valid covariances (as ``merge_maps`` checks them).

    Returns
    -------
    float
        √(mean over all landmarks of tr(Σ) / 2).
    """
    return float(np.sqrt(np.mean(np.concatenate([np.trace(cov_p, axis1=1, axis2=2),
                                                 np.trace(cov_q, axis1=1, axis2=2)]) / 2)))


def merge_maps(P, Q, sigma=None, *, tau=DEFAULT_TAU, method=DEFAULT_METHOD, objective="lr", cov_p=None,
               cov_q=None, rng=None) -> MergeResult:
    """Match two landmark maps and build their maximum-likelihood combination.

    Parameters
    ----------
    P, Q : (n, 2) array_like
        Landmark estimates of map p and map q, each in its own frame; n >= 3,
        finite, distinct, not all collinear, real coordinates of magnitude at
        most 1e50 spanning at least 1e-50 (rescale other units).
    sigma : float, optional
        Per-coordinate standard deviation of one landmark's position, in map
        units (metres for metric maps), in [1e-50, 1e50]. May be left out when ``cov_p``
        and ``cov_q`` are given: then it is their ``pooled_sigma``, the σ
        of the stages that take one (the triangle statistic and its
        threshold). Measured on 100-landmark maps
        (``python -m experiments.sigma``): ``consensus`` loses nothing when
        σ is overstated 2x, but at half the true σ its gates reject about a
        fifth of the true pairs; when unsure, overstate σ.
    tau : float or str, default ``"chi2:0.01"``
        Threshold: a log-LR value, or ``"chi2:P"`` for the χ²₃ rule
        ``log τ = -½ χ²₃⁻¹(1 - P)``.
    method : str, default ``"consensus_count"``
        A name in ``METHODS``. ``"consensus_count"`` (the default) or
        ``"consensus"`` is the one to use on real maps: it verifies that the
        matched triangles agree on one rigid motion, associates every
        landmark and refuses matches chance could explain. The two are the
        same on maps of more than 50 landmarks; on smaller ones
        ``consensus_count`` accepts by the number of associations, at
        levels set for a false-merge rate of at most 1e-3 per map pair, and
        finds more. ``"paper"`` is the seed paper's method as published.
    objective : {"lr", "loglr"}
        LP objective: Σ Λ as in the paper, or Σ log Λ.
    cov_p, cov_q : (n, 2, 2) or (n,) array_like, optional
        Each landmark's own covariance in its map's frame, or its variance
        per coordinate (given together). ``consensus``'s association gates
        and acceptance test use them instead of σ², and every method fuses
        matched landmarks by information weighting (the row covariance is
        the information sum's inverse, q's covariances rotated into p's
        frame). The transform is still the closed-form fit.
    rng : None, int, SeedSequence or Generator
        Randomness of randomised baselines (astroalign's RANSAC); default:
        a generator seeded by the two maps, so the same maps give the same
        answer.

    Returns
    -------
    MergeResult

    Raises
    ------
    ValueError
        On invalid maps, ``sigma``, ``tau``, ``method``, ``objective`` or
        variances.
    """
    P, Q, sigma, cov_p, cov_q = _check_pair(P, Q, sigma, cov_p, cov_q)
    covs = (None if cov_p is None else cov_p[None], None if cov_q is None else cov_q[None])
    return _merge(P[None], Q[None], np.array([sigma]), covs, _Options(tau, method, objective, rng)).result(0)


def _check_pair(P, Q, sigma, cov_p, cov_q):
    """One map pair's maps, covariances and σ (``pooled_sigma`` when None), checked as ``merge_maps`` takes them."""
    P, Q = check_points(P, "P"), check_points(Q, "Q")
    cov_p, cov_q = check_covariances(cov_p, len(P), "cov_p"), check_covariances(cov_q, len(Q), "cov_q")
    if sigma is None:
        if cov_p is None or cov_q is None:
            raise ValueError("sigma is needed unless cov_p and cov_q give every landmark's covariance")
        sigma = pooled_sigma(cov_p, cov_q)
    sigma = check_sigma(sigma)
    if (cov_p is None) != (cov_q is None):
        raise ValueError("cov_p and cov_q must be given together")
    return P, Q, sigma, cov_p, cov_q


@dataclass(frozen=True)
class _Options:
    """The options ``merge_maps`` and ``merge_batch`` share, as their callers gave them."""

    tau: float | str
    method: str
    objective: str
    rng: object


def _merge(P, Q, sigma, covs, options: _Options) -> MergeBatch:
    """The checks ``merge_maps`` and ``merge_batch`` share, then the method's two stages.

    ``covs``: the map pairs' (cov_p, cov_q), checked (or None each).
    """
    log_tau = resolve_log_tau(options.tau)
    get_method(options.method)
    check_objective(options.objective)
    rng = check_rng(options.rng)
    match = match_stage(P, Q, sigma, options.method, options.objective, log_tau)
    return merge_at(P, Q, sigma, match, np.full(len(P), log_tau), method=options.method, cov_p=covs[0],
                    cov_q=covs[1], rng=rng)


def _check_batch(maps, name: str) -> np.ndarray:
    arr = float_array(maps, f"{name} must be a (B, n, 2) array of real numbers: B maps of one size n "
                            "(merge_maps takes maps of any sizes, one pair at a time)")
    if arr.ndim != 3 or arr.shape[2] != 2 or arr.shape[1] < 3 or arr.shape[0] < 1:
        raise ValueError(f"{name} must have shape (B, n, 2) with B >= 1 and n >= 3, got {arr.shape}")
    check_finite(arr, name)
    check_geometry(arr, name, indexed=True)
    return arr


@dataclass(frozen=True)
class ResidualMatch:
    """A second rigid match among the landmarks a merge left unpaired (``residual_match``).

    Attributes
    ----------
    matched : bool
        Whether the unpaired landmarks hold a significant match of their own.
    theta : float
        Its rotation (``q ≈ R(θ) p + t``); NaN when not matched.
    t : (2,) ndarray
        Its translation; NaN when not matched.
    pairs : (K, 2) int ndarray
        Its correspondences, as rows of the whole maps (p row, q row).
    rotation_offset : float
        Its rotation minus the first merge's, wrapped to (-π, π]; NaN when
        not matched.
    """

    matched: bool
    theta: float
    t: np.ndarray
    pairs: np.ndarray
    rotation_offset: float


def residual_match(P, Q, result: MergeResult, sigma=None, tau=DEFAULT_TAU, cov_p=None, cov_q=None) -> ResidualMatch:
    """Look for a second rigid match among the landmarks a merge left unpaired.

    When one rigid motion relates two maps, the landmarks a merge leaves
    unpaired are those only one map holds (and common ones the noise hid),
    and chance seldom gives them a significant match of their own:
    ``consensus`` accepts a match only when its expected number of chance
    equivalents is below ``consensus.match_level`` of the leftover maps'
    size (``search.SEARCH_NFA`` for its global search). A second match means the
    maps are not one rigid body: drift bent one of them, so part of their
    overlap moved rigidly against the rest. The merge then aligned the
    larger part, and the common landmarks of the other part appear twice in
    its combined map. (After a method that can merge by chance, such as
    ``"paper"``, a second match may instead be the right one.) Too few
    landmarks left in the bent part (a handful) hold no significant match,
    so "no second match" does not prove a map rigid.

    Parameters
    ----------
    P, Q : (n, 2) array_like
        The maps ``result`` merged.
    result : MergeResult
        A matched merge of ``P`` and ``Q`` (any method).
    sigma, tau, cov_p, cov_q
        As for ``merge_maps``; pass what the first merge was given. Without
        ``sigma``, it is ``pooled_sigma`` over the whole maps, as there.

    Returns
    -------
    ResidualMatch
        ``consensus`` on the unpaired landmarks, indices into the whole maps.

    Raises
    ------
    ValueError
        On invalid maps, ``sigma``, ``tau`` or covariances, or a ``result``
        that is not a matched merge of maps this size.
    """
    P, Q, sigma, cov_p, cov_q = _check_pair(P, Q, sigma, cov_p, cov_q)
    resolve_log_tau(tau)
    if not isinstance(result, MergeResult):
        raise ValueError(f"result must be the MergeResult of merge_maps(P, Q, ...), got {type(result).__name__}")
    if not result.matched:
        raise ValueError("result must be a matched merge (result.matched is False)")
    if np.any(result.pairs[:, 0] >= len(P)) or np.any(result.pairs[:, 1] >= len(Q)):
        raise ValueError("result pairs rows beyond P or Q; pass the maps it merged")
    none = ResidualMatch(False, float("nan"), np.full(2, np.nan), np.empty((0, 2), np.intp), float("nan"))
    rest = _unpaired(P, Q, result)
    if rest is None:
        return none
    rest_p, rest_q = rest
    second = merge_maps(P[rest_p], Q[rest_q], sigma, tau=tau, method="consensus",
                        cov_p=None if cov_p is None else cov_p[rest_p], cov_q=None if cov_q is None else cov_q[rest_q])
    if not second.matched:
        return none
    pairs = np.stack([rest_p[second.pairs[:, 0]], rest_q[second.pairs[:, 1]]], axis=1)
    return ResidualMatch(True, second.theta, second.t, pairs, float(wrap_angle(second.theta - result.theta)))


def _unpaired(P, Q, result: MergeResult):
    """The rows of P and of Q that ``result`` left unpaired, or None when they hold no triangle."""
    rest_p = np.setdiff1d(np.arange(len(P)), result.pairs[:, 0])
    rest_q = np.setdiff1d(np.arange(len(Q)), result.pairs[:, 1])
    if min(len(rest_p), len(rest_q)) < 3:
        return None
    try:
        check_geometry(P[rest_p][None], "P")
        check_geometry(Q[rest_q][None], "Q")
    except ValueError:
        # What is left lies on one line: no triangle, no rigid match to find.
        return None
    return rest_p, rest_q


#: ``rigid_check`` flags a merge when a landmark pair lies farther from the fitted motion than a correct
#: merge's pairs would with this probability, all pairs together (Bonferroni over the K pairs).
RIGID_CHECK_P = 0.01
#: Methods without an acceptance test of their own: ``rigid_check`` is the only check of their merges.
UNTESTED_METHODS = ("paper", "cyclic", "groth", "astroalign")


@dataclass(frozen=True)
class RigidCheck:
    """Whether a merge's landmark pairs agree on its one rigid motion (``rigid_check``).

    Attributes
    ----------
    agree : bool
        No pair beyond ``bound``.
    n_outliers : int
        Pairs whose normalised squared residual exceeds ``bound``.
    bound : float
        The χ²₂ quantile every pair of a correct merge stays below with probability 1 - ``RIGID_CHECK_P``:
        ``2 log(K / RIGID_CHECK_P)``.
    max_stat : float
        The largest normalised squared residual (χ²₂ for a true pair).
    """

    agree: bool
    n_outliers: int
    bound: float
    max_stat: float


def rigid_check(P, Q, result: MergeResult, sigma=None, cov_p=None, cov_q=None) -> RigidCheck:
    """Test a matched merge's landmark pairs against its fitted rigid motion.

    Each pair's residual ``d = q_j - (R(θ) p_i + t)`` has, for a true pair,
    covariance ``Σ_q,j + R Σ_p,i Rᵀ`` (``2σ² I`` without covariances), so
    ``dᵀ Σ⁻¹ d`` is about χ²₂ (a little smaller: the fit absorbs 3 of the 2K
    degrees of freedom). A wrong pair, or a match that is wrong as a whole,
    leaves residuals far beyond the bound. ``consensus`` and ``search``
    accept only matches that pass a stricter test; for the methods in
    ``UNTESTED_METHODS`` this is the only sign of a wrong merge.

    Parameters
    ----------
    P, Q : (n, 2) array_like
        The maps ``result`` merged.
    result : MergeResult
        A matched merge of ``P`` and ``Q``.
    sigma, cov_p, cov_q
        As for ``merge_maps``.

    Returns
    -------
    RigidCheck

    Raises
    ------
    ValueError
        As ``residual_match``: invalid maps, σ or covariances, or a ``result`` that is not a matched merge
        of maps this size.
    """
    P, Q, sigma, cov_p, cov_q = _check_pair(P, Q, sigma, cov_p, cov_q)
    if not isinstance(result, MergeResult) or not result.matched:
        raise ValueError("result must be a matched MergeResult of merge_maps(P, Q, ...)")
    if np.any(result.pairs[:, 0] >= len(P)) or np.any(result.pairs[:, 1] >= len(Q)):
        raise ValueError("result pairs rows beyond P or Q; pass the maps it merged")
    i, j = result.pairs[:, 0], result.pairs[:, 1]
    R = rotation(result.theta)
    d = Q[j] - (P[i] @ R.T + result.t)
    cov = (np.full(len(i), 2 * sigma**2)[:, None, None] * np.eye(2) if cov_p is None
           else cov_q[j] + R @ cov_p[i] @ R.T)
    stat = np.einsum("ki,kij,kj->k", d, np.linalg.inv(cov), d)
    bound = float(2 * np.log(len(i) / RIGID_CHECK_P))
    outliers = int(np.sum(stat > bound))
    return RigidCheck(outliers == 0, outliers, bound, float(stat.max(initial=0.0)))
