"""Maximum-likelihood combined map (paper eq. 15).

From the matched landmark set K, the n-point closed form gives θ*, t* and
the fused landmarks µ*. The combined map, in map p's frame, is

    [ µ* ;  p-only landmarks ;  R(θ*)ᵀ (q-only landmarks - t*) ]

and every row records where it came from.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .statistic import Alignment, _align, mapped_covariance, rotation


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

    @functools.cached_property
    def cov(self) -> np.ndarray:
        cov = np.broadcast_to(self.sigma**2 * np.eye(2), (len(self.points), 2, 2)).copy()
        if self.alignment is not None:
            fused, only_q = self.origin == "fused", self.origin == "q"
            cov[fused] = self.alignment.mu_cov
            cov[only_q] = mapped_covariance(self.points[only_q], self.alignment.theta,
                                            self.alignment.cov, self.sigma**2)
        return cov


def combine_maps(P: np.ndarray, Q: np.ndarray, pairs: np.ndarray, sigma: float):
    """Align on the paired landmarks and build the combined map (15).

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
        The two maps, validated.
    pairs : (K, 2) int ndarray
        One-to-one landmark correspondences (p index, q index), K >= 2.
    sigma : float
        Noise standard deviation.

    Returns
    -------
    alignment : Alignment
    combined : CombinedMap
    """
    alignment: Alignment = _align(P[pairs[:, 0]], Q[pairs[:, 1]], sigma)
    only_p, only_q = _unpaired(P.shape[0], pairs[:, 0]), _unpaired(Q.shape[0], pairs[:, 1])
    q_in_p = (Q[only_q] - alignment.t) @ rotation(alignment.theta)
    k, n_p, n_q = pairs.shape[0], only_p.size, only_q.size
    combined = CombinedMap(
        points=np.concatenate([alignment.mu, P[only_p], q_in_p]),
        origin=np.array(["fused"] * k + ["p"] * n_p + ["q"] * n_q, dtype=object),
        index_p=np.concatenate([pairs[:, 0], only_p, np.full(n_q, -1)]).astype(np.intp),
        index_q=np.concatenate([pairs[:, 1], np.full(n_p, -1), only_q]).astype(np.intp),
        sigma=sigma,
        alignment=alignment,
    )
    return alignment, combined


def _unpaired(n: int, paired: np.ndarray) -> np.ndarray:
    mask = np.ones(n, dtype=bool)
    mask[paired] = False
    return np.flatnonzero(mask)


def p_only_map(P: np.ndarray, sigma: float) -> CombinedMap:
    """The combined map when nothing matched: map p alone, in its own frame."""
    n = P.shape[0]
    return CombinedMap(
        points=P.copy(),
        origin=np.array(["p"] * n, dtype=object),
        index_p=np.arange(n, dtype=np.intp),
        index_q=np.full(n, -1, dtype=np.intp),
        sigma=sigma,
        alignment=None,
    )
