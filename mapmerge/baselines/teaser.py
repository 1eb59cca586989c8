"""TEASER++ (Yang, Shi & Carlone, 2020) as a baseline (built from source: tools/build_peers.sh).

TEASER++ is 3-D only: the landmarks are given z = 0. It takes putative
correspondences (``associations.putative_associations``: all-to-all on
small maps), prunes them to the maximum clique of the graph of pairs whose
translation- and rotation-invariant measurements agree within the noise
bound (exact, pmc), then solves scale-free truncated least squares for the
rotation (GNC-TLS) and the translation. The noise bound β is
``TEASER_NOISE_SIGMAS`` σ: a residual q - (Rp + t) of two noisy landmarks
has per-coordinate standard deviation √2 σ, so β is three of those. Its
inlier set is the max-clique correspondences whose residual under its
solution is within β, one-to-one (the first of each landmark). TEASER++
has no acceptance test of its own, so the merge is accepted when the
inliers number at least ``TEASER_MIN_INLIERS`` for its map size (set on unrelated calibration pairs, docs/peers.md). The
transform is the closed-form 2-D rigid fit on the inliers
(``result.build_batch``).
"""

from __future__ import annotations

import numpy as np

from ..result import MergeBatch
from ..triangles import TriangleBatch
from .associations import merge_by_inliers, one_to_one, putative_associations

#: TEASER++'s noise bound β in units of σ (three standard deviations of a residual coordinate, √2 σ each).
TEASER_NOISE_SIGMAS = 3 * np.sqrt(2)
#: GNC-TLS's factor and iteration cap (TEASER++'s defaults).
TEASER_GNC_FACTOR = 1.4
TEASER_MAX_ITERATIONS = 100

#: Acceptance: the least inlier count accepted, per map size (landmarks of the smaller map), each
#: letting through at most 1 of 1,000 unrelated pairs at 30 dB, seeds 10**6 + i
#: (results/peers/calibration.md); ``associations.min_inliers`` applies it.
TEASER_MIN_INLIERS = {10: 5, 20: 7, 100: 9}


def _module():
    try:
        import teaserpp_python
    except ImportError as exc:  # built from source
        raise ImportError("method='teaser' needs TEASER++'s Python bindings: build them with tools/build_peers.sh "
                          "--teaser DIR --pmc DIR --spectra DIR --tinyply DIR (docs/peers.md)") from exc
    return teaserpp_python


def teaser_pairs(P: np.ndarray, Q: np.ndarray, sigma: float) -> np.ndarray:
    """TEASER++'s inlier correspondences (K, 2), one-to-one, sorted by p's index."""
    teaser = _module()
    params = teaser.RobustRegistrationSolver.Params()
    params.noise_bound = TEASER_NOISE_SIGMAS * sigma
    params.cbar2 = 1.0
    params.estimate_scaling = False
    params.rotation_estimation_algorithm = teaser.RotationEstimationAlgorithm.GNC_TLS
    params.rotation_gnc_factor = TEASER_GNC_FACTOR
    params.rotation_max_iterations = TEASER_MAX_ITERATIONS
    params.rotation_cost_threshold = 1e-12
    A = putative_associations(P, Q)
    src = np.vstack([P[A[:, 0]].T, np.zeros(len(A))])  # z = 0: TEASER++ has no 2-D mode
    dst = np.vstack([Q[A[:, 1]].T, np.zeros(len(A))])
    solver = teaser.RobustRegistrationSolver(params)
    solver.solve(src, dst)
    sol = solver.getSolution()
    clique = np.asarray(solver.getInlierMaxClique(), dtype=np.intp).ravel()
    if len(clique) == 0:
        return np.empty((0, 2), dtype=np.intp)
    resid = np.linalg.norm(dst[:, clique] - (sol.rotation @ src[:, clique] + sol.translation[:, None]), axis=0)
    return one_to_one(A[clique[resid <= params.noise_bound]])


def merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, rng=None) -> MergeBatch:
    """TEASER++ on B map pairs (``rng`` unused: the method is deterministic)."""
    return merge_by_inliers("teaser", teaser_pairs, TEASER_MIN_INLIERS, P, Q, sigma, tri_p, tri_q)
