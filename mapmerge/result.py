"""What a merge returns: ``MergeResult`` for one map pair, ``MergeBatch`` for many.

Every method (the paper's, its variants, the baselines) ends the same way:
landmark correspondences go to ``build_batch``, which assembles the
``MergeBatch`` from the n-point closed form of every map pair with at least
``MIN_MATCHED_LANDMARKS`` correspondences (``alignment.fit_matched``) and
the combined maps (eq. 15, ``combining.combine_batch``). A ``MergeBatch``
holds ragged arrays tagged by map pair; ``MergeBatch.result(b)`` is map
pair b's ``MergeResult``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .alignment import Alignment, fit_matched
from .combining import FUSED, ORIGINS, CombinedBatch, CombinedMap, combine_batch
from .triangles import TriangleBatch, Triangles

#: Fewest landmark correspondences accepted as a match: one triangle's worth.
MIN_MATCHED_LANDMARKS = 3


@dataclass(frozen=True)
class MergeResult:
    """Outcome of ``merge_maps``.

    Attributes
    ----------
    matched : bool
        False when no match was found ("no match"): then ``theta`` and ``t``
        are NaN, ``alignment`` is None and ``merged`` is map p alone.
    theta : float
        Rotation of map q relative to map p (``q ≈ R(θ) p + t``).
    t : (2,) ndarray
        Translation.
    pairs : (K, 2) int ndarray
        Landmark correspondences (p index, q index).
    n_conflicts : int
        Correspondences dropped because a landmark was claimed twice.
    triangle_pairs : (M, 2) int ndarray
        Tentative triangle pairs (indices into ``tri_p``/``tri_q``).
    triangle_log_lr : (M,) ndarray
        Their log Λ.
    declared : (M,) bool ndarray
        Pairs declared matched.
    log_tau : float
        The threshold used, as a log-LR (NaN for methods without one).
    merged : (N, 2) ndarray
        The combined map in p's frame; ``origin``, ``index_p``, ``index_q``
        give each row's provenance and ``cov`` its covariance.
    """

    matched: bool
    theta: float
    t: np.ndarray
    pairs: np.ndarray
    n_conflicts: int
    triangle_pairs: np.ndarray
    triangle_log_lr: np.ndarray
    declared: np.ndarray
    log_tau: float
    tri_p: Triangles
    tri_q: Triangles
    alignment: Alignment | None
    combined: CombinedMap
    method: str

    @property
    def merged(self) -> np.ndarray:
        return self.combined.points

    @property
    def origin(self) -> np.ndarray:
        return self.combined.origin

    @property
    def index_p(self) -> np.ndarray:
        return self.combined.index_p

    @property
    def index_q(self) -> np.ndarray:
        return self.combined.index_q

    @property
    def cov(self) -> np.ndarray:
        """(N, 2, 2) covariance of each combined-map row."""
        return self.combined.cov


@dataclass(frozen=True)
class MergeBatch:
    """Outcome of merging B map pairs (see ``build_batch`` for the fields)."""

    method: str
    P: np.ndarray
    Q: np.ndarray
    sigma: np.ndarray
    log_tau: np.ndarray
    tri_p: TriangleBatch
    tri_q: TriangleBatch
    tri_trial: np.ndarray
    triangle_pairs: np.ndarray
    triangle_log_lr: np.ndarray
    declared: np.ndarray
    pair_trial: np.ndarray
    pairs: np.ndarray
    n_conflicts: np.ndarray
    matched: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    cost: np.ndarray
    combined: CombinedBatch

    def __len__(self) -> int:
        return len(self.P)

    def with_covariances(self, cov_p: np.ndarray, cov_q: np.ndarray) -> "MergeBatch":
        """The same merges with the combined maps fused by information weighting (``combine_batch``)."""
        return dataclasses.replace(self, combined=combine_batch(self.P, self.Q, self.pair_trial, self.pairs,
                                                                self.matched, self.theta, self.t,
                                                                cov_p=cov_p, cov_q=cov_q))

    def result(self, b: int) -> MergeResult:
        """Map pair b's ``MergeResult``."""
        sigma = float(self.sigma[b])
        pairs = self.pairs[self.pair_trial == b]
        rows = slice(self.combined.offsets[b], self.combined.offsets[b + 1])
        origin = self.combined.origin[rows]
        points = self.combined.points[rows]
        alignment = None
        if self.matched[b]:
            alignment = Alignment(theta=float(self.theta[b]), t=self.t[b], mu=points[origin == FUSED],
                                  cost=float(self.cost[b]), log_lr=-float(self.cost[b]) / (2.0 * sigma**2),
                                  dof=2 * len(pairs) - 3, sigma=sigma)
        tri = self.tri_trial == b
        return MergeResult(
            matched=bool(self.matched[b]), theta=float(self.theta[b]), t=self.t[b], pairs=pairs,
            n_conflicts=int(self.n_conflicts[b]), triangle_pairs=self.triangle_pairs[tri],
            triangle_log_lr=self.triangle_log_lr[tri], declared=self.declared[tri],
            log_tau=float(self.log_tau[b]), tri_p=self.tri_p[b], tri_q=self.tri_q[b], alignment=alignment,
            combined=CombinedMap(points=points, origin=ORIGINS[origin], index_p=self.combined.index_p[rows],
                                 index_q=self.combined.index_q[rows], sigma=sigma, alignment=alignment,
                                 row_cov=None if self.combined.cov is None else self.combined.cov[rows]),
            method=self.method,
        )


def build_batch(*, method: str, P: np.ndarray, Q: np.ndarray, sigma: np.ndarray, log_tau: np.ndarray,
                tri_p: TriangleBatch, tri_q: TriangleBatch, tri_trial: np.ndarray, triangle_pairs: np.ndarray,
                triangle_log_lr: np.ndarray, declared: np.ndarray, pair_trial: np.ndarray, pairs: np.ndarray,
                n_conflicts: np.ndarray) -> MergeBatch:
    """Fit and combine B map pairs from their landmark correspondences.

    Parameters
    ----------
    method : str
        Name of the method that found the correspondences.
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
        The maps.
    sigma, log_tau : (B,) ndarray
        Noise level and threshold of each map pair (NaN: no threshold).
    tri_p, tri_q : TriangleBatch
        The maps' triangles.
    tri_trial, triangle_pairs, triangle_log_lr, declared : (M,), (M, 2), (M,), (M,) ndarray
        The tentative triangle pairs reported (map pair, triangle indices,
        log Λ, declared or not), sorted by map pair.
    pair_trial, pairs : (K,), (K, 2) int ndarray
        One-to-one landmark correspondences and their map pair, sorted by
        map pair. Map pairs with fewer than ``MIN_MATCHED_LANDMARKS`` are
        "no match" (their correspondences are still reported).
    n_conflicts : (B,) int ndarray
        Correspondences dropped as conflicting.

    Returns
    -------
    MergeBatch
    """
    matched, theta, t, cost = fit_matched(P, Q, pair_trial, pairs, MIN_MATCHED_LANDMARKS)
    return MergeBatch(
        method=method, P=P, Q=Q, sigma=sigma, log_tau=log_tau, tri_p=tri_p, tri_q=tri_q,
        tri_trial=tri_trial, triangle_pairs=triangle_pairs, triangle_log_lr=triangle_log_lr,
        declared=declared, pair_trial=pair_trial, pairs=pairs, n_conflicts=n_conflicts,
        matched=matched, theta=theta, t=t, cost=cost,
        combined=combine_batch(P, Q, pair_trial, pairs, matched, theta, t),
    )


def build_from_parts(*, method: str, P: np.ndarray, Q: np.ndarray, sigma: np.ndarray, log_tau: np.ndarray,
                     tri_p: TriangleBatch, tri_q: TriangleBatch, parts) -> MergeBatch:
    """``build_batch`` from per-map-pair results of a method that runs one pair at a time.

    ``parts[b]`` is map pair b's ``(triangle_pairs, triangle_log_lr, declared, pairs, n_conflicts)``.
    """
    def stacked(k, shape=(-1,)):
        return np.concatenate([p[k] for p in parts]).reshape(shape)

    def trial_of(k):
        return np.repeat(np.arange(len(parts)), [len(p[k]) for p in parts])

    return build_batch(
        method=method, P=P, Q=Q, sigma=sigma, log_tau=log_tau, tri_p=tri_p, tri_q=tri_q,
        tri_trial=trial_of(1), triangle_pairs=stacked(0, (-1, 2)).astype(np.intp),
        triangle_log_lr=stacked(1).astype(float), declared=stacked(2).astype(bool),
        pair_trial=trial_of(3), pairs=stacked(3, (-1, 2)).astype(np.intp),
        n_conflicts=np.array([p[4] for p in parts], dtype=np.int64),
    )
