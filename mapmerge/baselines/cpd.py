"""Coherent Point Drift (Myronenko & Song, 2010), rigid, as a baseline (optional extra ``[peers]``).

CPD fits map p's landmarks as the centroids of a Gaussian mixture (with a
uniform outlier component of weight ``CPD_OUTLIER_WEIGHT``) to map q's
landmarks by EM over a rigid transform and a shared variance, from
``pycpd.RigidRegistration``, whose M-step also fits a scale: here the
scale is held at 1 (the rotation is pycpd's, the translation and variance
the M-step's without scale), since map frames differ by a rotation and a
translation only. EM is local, so it is started from ``CPD_STARTS``
rotations of q about its centroid, evenly spaced, with the two centroids
superposed.

CPD's own variance does not tell related maps from unrelated ones (on
small maps EM shrinks it onto a few chance fits), so after EM the
posteriors are evaluated once more at the known noise, variance 2σ² per
coordinate (two noisy landmarks), with the same outlier weight, and a pair
(i of p, j of q) is an inlier when its posterior exceeds ``CPD_POSTERIOR``
and each is the other's most probable partner (one-to-one). The start
with the most inliers wins (ties: the first). CPD has no acceptance test,
so the merge is accepted when the inliers number at least ``CPD_MIN_INLIERS`` for its map size (and at least
``result.MIN_MATCHED_LANDMARKS``); that threshold was set on unrelated pairs
whose seeds are disjoint from the reported ones (docs/peers.md). The
transform is then the closed-form rigid fit on the inlier pairs
(``result.build_batch``).
"""

from __future__ import annotations

import numpy as np

from ..result import MergeBatch
from ..triangles import TriangleBatch
from .associations import merge_by_inliers, rotate_about_centroid

#: Starting rotations of map q, evenly spaced over the circle (EM is local).
CPD_STARTS = 12
#: Weight of CPD's uniform outlier component (about the share of landmarks of one map the other lacks).
CPD_OUTLIER_WEIGHT = 0.25
#: Posterior above which a landmark pair is an inlier (and mutual best: one-to-one).
CPD_POSTERIOR = 0.5
#: EM iterations per start and the change in its objective at which it stops (pycpd's ``tolerance``).
CPD_MAX_ITERATIONS = 100
CPD_TOLERANCE = 1e-5
#: Floor of EM's variance (squared map units), so that a collapse onto exact fits stays finite.
CPD_MIN_VARIANCE = 1e-12

#: Acceptance: the least inlier count accepted, per map size (landmarks of the smaller map), each
#: letting through at most 1 of 1,000 unrelated pairs at 30 dB, seeds 10**6 + i
#: (results/peers/calibration.md, 200 pairs at 100 landmarks); ``associations.min_inliers`` applies it.
CPD_MIN_INLIERS = {10: 6, 20: 7, 100: 13}


def _module():
    try:
        import pycpd
    except ImportError as exc:  # optional extra
        raise ImportError("method='cpd' needs the optional package: pip install 'mapmerge[peers]'") from exc
    return pycpd


def _registration(pycpd):
    """``pycpd.RigidRegistration`` with its scale held at 1 (a subclass, built once pycpd is imported)."""

    class FixedScaleRigid(pycpd.RigidRegistration):
        def update_transform(self):
            super().update_transform()  # pycpd's rotation (its SVD does not depend on the scale)
            self.s = 1.0
            self.t = (self.Pt1 @ self.X - (self.P1 @ self.Y) @ self.R) / self.Np

        def update_variance(self):
            # The M-step's variance and objective at scale 1 (pycpd's assume the fitted scale).
            q_prev = self.q
            ssd = self.Pt1 @ np.sum(self.X_hat ** 2, axis=1) - 2 * np.trace(self.A @ self.R) + self.YPY
            self.sigma2 = max(ssd / (self.Np * self.D), CPD_MIN_VARIANCE)
            self.q = ssd / (2 * self.sigma2) + self.D * self.Np / 2 * np.log(self.sigma2)
            self.diff = abs(self.q - q_prev)

    return FixedScaleRigid


def cpd_pairs(P: np.ndarray, Q: np.ndarray, sigma: float) -> np.ndarray:
    """CPD's inlier pairs (K, 2) of its best start, sorted by p's index (see the module docstring).

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
        The two maps' landmarks.
    sigma : float
        Their noise standard deviation.

    Returns
    -------
    (K, 2) int ndarray
        Mutual-best pairs with posterior above ``CPD_POSTERIOR`` at the known noise.
    """
    Rigid = _registration(_module())
    var = 2 * sigma ** 2
    area = np.prod(np.ptp(Q, axis=0))
    # The uniform component's density against the Gaussians' normaliser, as in CPD's E-step.
    outlier = CPD_OUTLIER_WEIGHT / (1 - CPD_OUTLIER_WEIGHT) * 2 * np.pi * var * len(P) / area
    rows = np.arange(len(P))
    best = np.empty((0, 2), np.intp)
    for angle in np.arange(CPD_STARTS) * (2 * np.pi / CPD_STARTS):
        X = rotate_about_centroid(Q, angle) - Q.mean(axis=0) + P.mean(axis=0)
        reg = Rigid(X=X, Y=P, w=CPD_OUTLIER_WEIGHT, max_iterations=CPD_MAX_ITERATIONS, tolerance=CPD_TOLERANCE)
        reg.register()
        g = np.exp(-np.sum((reg.TY[:, None] - X[None]) ** 2, axis=2) / (2 * var))
        post = g / (g.sum(axis=0) + outlier)  # (n_p, n_q): P(centroid i | landmark j)
        i_best, j_best = np.argmax(post, axis=1), np.argmax(post, axis=0)
        i = np.flatnonzero((j_best[i_best] == rows) & (post[rows, i_best] > CPD_POSTERIOR))
        if len(i) > len(best):
            best = np.stack([i, i_best[i]], axis=1).astype(np.intp)
    return best


def merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, rng=None) -> MergeBatch:
    """CPD on B map pairs (``rng`` unused: the starts are fixed and EM is deterministic)."""
    return merge_by_inliers("cpd", cpd_pairs, CPD_MIN_INLIERS, P, Q, sigma, tri_p, tri_q)
