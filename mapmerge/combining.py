"""Maximum-likelihood combined map (paper eq. 15).

From the matched landmark set K, the n-point closed form gives θ*, t* and
the fused landmarks µ*. The combined map, in map p's frame, is

    [ µ* ;  p-only landmarks ;  R(θ*)ᵀ (q-only landmarks - t*) ]

and every row records where it came from. ``combine_batch`` builds the
combined maps of many map pairs at once (ragged rows tagged by trial); a
pair with no match keeps map p alone.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .alignment import Alignment, covariance_in_p_frame, mapped_covariance, rotate

#: Row origins, in the order they appear in a combined map.
ORIGINS = np.array(["fused", "p", "q"], dtype=object)
FUSED, ONLY_P, ONLY_Q = 0, 1, 2


@dataclass(frozen=True)
class CombinedMap:
    """Rows of the combined map with their provenance.

    Attributes
    ----------
    points : (N, 2) ndarray
        Landmarks in map p's frame.
    origin : (N,) ndarray of str
        ``"fused"``, ``"p"`` or ``"q"``.
    index_p, index_q : (N,) int ndarray
        Source landmark index in map p / map q, -1 where there is none.
    sigma : float
    alignment : Alignment or None
        The fit behind the fused and mapped rows (None: map p alone).
    cov : (N, 2, 2) ndarray
        Covariance of each row (computed on first use): µ* from the n-point
        fit, σ² I for p-only rows, σ² I plus the transform's uncertainty for
        mapped q-only rows.
    """

    points: np.ndarray
    origin: np.ndarray
    index_p: np.ndarray
    index_q: np.ndarray
    sigma: float
    alignment: Alignment | None
    row_cov: np.ndarray | None = None

    @functools.cached_property
    def cov(self) -> np.ndarray:
        if self.row_cov is not None:  # from the landmarks' own covariances (information-weighted fusion)
            return self.row_cov
        cov = np.broadcast_to(self.sigma**2 * np.eye(2), (len(self.points), 2, 2)).copy()
        if self.alignment is not None:
            fused, only_q = self.origin == "fused", self.origin == "q"
            cov[fused] = self.alignment.mu_cov
            cov[only_q] = mapped_covariance(self.points[only_q], self.alignment.theta,
                                            self.alignment.cov, self.sigma**2)
        return cov


@dataclass(frozen=True)
class CombinedBatch:
    """Combined maps of B map pairs as ragged rows.

    Attributes
    ----------
    trial : (R,) int ndarray
        Map pair of each row; rows of one pair are contiguous, fused rows
        first (in pair order), then p-only, then q-only rows.
    offsets : (B + 1,) int ndarray
    points : (R, 2) ndarray
        In each pair's map-p frame.
    origin : (R,) int8 ndarray
        ``FUSED``, ``ONLY_P`` or ``ONLY_Q`` (names in ``ORIGINS``).
    index_p, index_q : (R,) int ndarray
        Source landmark index, -1 where there is none.
    cov : (R, 2, 2) ndarray or None
        Row covariances when the landmarks' own covariances were given.
    """

    trial: np.ndarray
    offsets: np.ndarray
    points: np.ndarray
    origin: np.ndarray
    index_p: np.ndarray
    index_q: np.ndarray
    cov: np.ndarray | None = None


def combine_batch(P: np.ndarray, Q: np.ndarray, pair_trial: np.ndarray, pairs: np.ndarray,
                  matched: np.ndarray, theta: np.ndarray, t: np.ndarray, *, cov_p: np.ndarray | None = None,
                  cov_q: np.ndarray | None = None) -> CombinedBatch:
    """Eq. (15) for B map pairs, information-weighted when covariances are given.

    With equal isotropic noise a fused landmark is the midpoint µ* of p_i and
    q_j brought into p's frame. With per-landmark covariances (``cov_p``,
    ``cov_q``) it is the information-weighted mean of the two,
    ``(Σp⁻¹ + Σq'⁻¹)⁻¹ (Σp⁻¹ p + Σq'⁻¹ q')`` with ``q' = R(θ)ᵀ (q - t)`` and
    ``Σq' = R(θ)ᵀ Σq R(θ)``, and its covariance is that information sum's
    inverse; p-only rows keep Σp and q-only rows get Σq'. These row
    covariances leave out the fitted transform's own uncertainty, which
    matters where both maps know a landmark far better than the transform
    is known (far from the matched landmarks' centroid).

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    pair_trial : (K,) int ndarray
        Map pair of each correspondence, sorted; only matched pairs' are used.
    pairs : (K, 2) int ndarray
        Landmark correspondences (p index, q index).
    matched : (B,) bool ndarray
        Map pairs with a fit; the others keep map p alone.
    theta, t : (B,), (B, 2) ndarray
        The fitted transforms (``q ≈ R(θ) p + t``).
    cov_p, cov_q : (B, n_p, 2, 2), (B, n_q, 2, 2) ndarray, optional
        The landmarks' own covariances, each in its map's frame.

    Returns
    -------
    CombinedBatch
    """
    B, n_p, n_q = len(P), P.shape[1], Q.shape[1]
    use = matched[pair_trial]
    kt, pi, qi = pair_trial[use], pairs[use, 0], pairs[use, 1]
    mapped = rotate(-theta, Q - t[:, None, :])  # every q row in p's frame
    paired_p = np.zeros((B, n_p), bool)
    paired_q = ~matched[:, None] | np.zeros((B, n_q), bool)  # an unmatched pair keeps no q row
    paired_p[kt, pi] = True
    paired_q[kt, qi] = True
    tp_, ip = np.nonzero(~paired_p)
    tq_, iq = np.nonzero(~paired_q)
    trial = np.concatenate([kt, tp_, tq_])
    section = np.concatenate([np.full(kt.size, FUSED), np.full(tp_.size, ONLY_P), np.full(tq_.size, ONLY_Q)])
    fused, row_cov = 0.5 * (P[kt, pi] + mapped[kt, qi]), None
    if cov_p is not None:
        cov_q_in_p = covariance_in_p_frame(theta, cov_q)
        fused, fused_cov = _information_mean(P[kt, pi], cov_p[kt, pi], mapped[kt, qi], cov_q_in_p[kt, qi])
        row_cov = np.concatenate([fused_cov, cov_p[tp_, ip], cov_q_in_p[tq_, iq]])
    points = np.concatenate([fused, P[tp_, ip], mapped[tq_, iq]])
    index_p = np.concatenate([pi, ip, np.full(iq.size, -1)])
    index_q = np.concatenate([qi, np.full(ip.size, -1), iq])
    order = np.argsort(trial, kind="stable")  # sections already in row order within a trial
    count = np.bincount(trial, minlength=B)
    return CombinedBatch(trial=trial[order], offsets=np.concatenate(([0], np.cumsum(count))), points=points[order],
                         origin=section[order].astype(np.int8), index_p=index_p[order].astype(np.intp),
                         index_q=index_q[order].astype(np.intp), cov=None if row_cov is None else row_cov[order])


def _information_mean(p: np.ndarray, cov_p: np.ndarray, q: np.ndarray, cov_q: np.ndarray):
    """The information-weighted mean of paired points (K, 2) with covariances (K, 2, 2), and its covariance."""
    info_p, info_q = np.linalg.inv(cov_p), np.linalg.inv(cov_q)
    fused_cov = np.linalg.inv(info_p + info_q)
    fused = np.einsum("kij,kj->ki", fused_cov, np.einsum("kij,kj->ki", info_p, p)
                      + np.einsum("kij,kj->ki", info_q, q))
    return fused, fused_cov
