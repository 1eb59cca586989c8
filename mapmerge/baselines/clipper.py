"""CLIPPER (Lusk, Fathian & How, 2021) as a baseline (built from source: tools/build_peers.sh).

CLIPPER scores every two putative associations (``associations.
putative_associations``: all-to-all on small maps) by how well they keep
the distance between their landmarks, ``exp(-c²/2s²)`` for a distance
difference c below ε (0 above), and finds the densest consistent cluster
of associations by its projected gradient ascent (``CLIPPER.solve``) from
a random start u0, uniform on [0, 1) like CLIPPER's own but drawn from the
merge's generator (CLIPPER's own seeds from ``std::random_device``, so runs
would differ; without an ``rng``, one seeded by the maps' bytes). The
distance difference of two noisy landmark pairs has a standard deviation
of about 2σ, so s = ``CLIPPER_SIGMA_SIGMAS`` σ and ε =
``CLIPPER_EPS_SIGMAS`` σ. Its selected associations, one-to-one (the first
of each landmark in CLIPPER's order), are its inlier set. CLIPPER has no
acceptance test, so the merge is accepted when the inliers number at least ``CLIPPER_MIN_INLIERS`` for its map size (set on
unrelated calibration pairs, docs/peers.md). The transform is the
closed-form rigid fit on the inliers (``result.build_batch``).
"""

from __future__ import annotations

import numpy as np

from ..result import MergeBatch
from ..triangles import TriangleBatch
from .associations import merge_by_inliers, one_to_one, pair_generators, putative_associations

#: Spread of CLIPPER's consistency kernel, in units of σ (the distance difference's standard deviation).
CLIPPER_SIGMA_SIGMAS = 2.0
#: CLIPPER's consistency bound ε, in units of σ (three standard deviations of the distance difference).
CLIPPER_EPS_SIGMAS = 6.0

#: Acceptance: the least inlier count accepted, per map size (landmarks of the smaller map), each
#: letting through at most 1 of 1,000 unrelated pairs at 30 dB, seeds 10**6 + i
#: (results/peers/calibration.md); ``associations.min_inliers`` applies it.
CLIPPER_MIN_INLIERS = {10: 5, 20: 6, 100: 7}


def _module():
    try:
        import clipperpy
    except ImportError as exc:  # built from source
        raise ImportError("method='clipper' needs CLIPPER's Python bindings: build them with "
                          "tools/build_peers.sh --clipper DIR --pmc DIR (docs/peers.md)") from exc
    return clipperpy


def clipper_pairs(P: np.ndarray, Q: np.ndarray, sigma: float, rng=None) -> np.ndarray:
    """CLIPPER's selected associations (K, 2), one-to-one, sorted by p's index (its inlier set); ``rng``
    (seed or Generator; None: seeded by the maps' bytes) draws the start of its ascent."""
    clipperpy = _module()
    params = clipperpy.invariants.EuclideanDistanceParams()
    params.sigma, params.epsilon = CLIPPER_SIGMA_SIGMAS * sigma, CLIPPER_EPS_SIGMAS * sigma
    solver = clipperpy.CLIPPER(clipperpy.invariants.EuclideanDistance(params), clipperpy.Params())
    A = putative_associations(P, Q).astype(np.int32)
    solver.score_pairwise_consistency(np.asfortranarray(P.T, dtype=np.float64),
                                      np.asfortranarray(Q.T, dtype=np.float64), np.asfortranarray(A))
    gen = pair_generators(P[None], Q[None], rng)[0]
    solver.solve(gen.random(len(A)))
    return one_to_one(np.asarray(solver.get_selected_associations()).reshape(-1, 2))


def merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, rng=None) -> MergeBatch:
    """CLIPPER on B map pairs; ``rng`` (seed or Generator) draws each ascent's start (None: each pair's
    generator is seeded by its maps' bytes)."""
    return merge_by_inliers("clipper", clipper_pairs, CLIPPER_MIN_INLIERS, P, Q, sigma, tri_p, tri_q,
                            pair_generators(P, Q, rng))
