"""astroalign's ``find_transform`` as a baseline (optional extra ``[baselines]``).

The two point lists are handed to ``astroalign.find_transform`` with the
coordinates scaled so that its pixel tolerance equals
``ASTROALIGN_TOL_SIGMAS`` σ. astroalign raises when it finds no transform:
that is reported as "no match"; a wrong transform is kept and shows up in
the errors.

Its RANSAC shuffles candidates with ``numpy.random.default_rng()`` and
``find_transform`` takes no seed (astroalign 2.6). So that the baseline is
reproducible, ``numpy.random.default_rng`` called without a seed from the
thread running the call returns the caller's generator for the duration of
the call (and only then); any other call, and any call from another thread,
gets numpy's own ``default_rng``, and nothing global is seeded. Calls from
several threads take turns. Without a generator, one seeded by the two
maps' bytes is used, so the same maps give the same answer.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np

from ..result import MergeBatch, build_from_parts
from ..triangles import TriangleBatch
from .associations import pair_generators

#: astroalign's pixel tolerance (astroalign.PIXEL_TOL) is set to this many σ.
ASTROALIGN_TOL_SIGMAS = 3.0


def _module():
    try:
        import astroalign
    except ImportError as exc:  # optional extra
        raise ImportError("method='astroalign' needs the optional package: pip install 'mapmerge[baselines]'") from exc
    return astroalign


def astroalign_pairs(P: np.ndarray, Q: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Landmark correspondences (K, 2) that astroalign's transform rests on (empty: none)."""
    astroalign = _module()
    scale = astroalign.PIXEL_TOL / (ASTROALIGN_TOL_SIGMAS * sigma)
    try:
        with _ransac_rng(rng):
            _, (src, dst) = astroalign.find_transform(P * scale, Q * scale, max_control_points=max(len(P), len(Q)))
    except (astroalign.MaxIterError, ValueError):
        return np.empty((0, 2), dtype=np.intp)
    # astroalign returns matched coordinates; recover the landmark indices.
    ip = np.argmin(np.linalg.norm(P[None] * scale - src[:, None], axis=2), axis=1)
    iq = np.argmin(np.linalg.norm(Q[None] * scale - dst[:, None], axis=2), axis=1)
    # Keep the first match of every landmark so the pairs are one-to-one.
    first = np.zeros(len(ip), bool)
    first[np.unique(ip, return_index=True)[1]] = True
    first &= np.isin(np.arange(len(iq)), np.unique(iq, return_index=True)[1])
    pairs = np.stack([ip[first], iq[first]], axis=1).astype(np.intp)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def merge(P, Q, sigma, tri_p: TriangleBatch, tri_q: TriangleBatch, rng=None) -> MergeBatch:
    """astroalign on B map pairs; ``rng`` (seed or Generator) drives its RANSAC."""
    gens = pair_generators(P, Q, rng)
    empty = (np.empty((0, 2), dtype=np.intp), np.empty(0), np.empty(0, bool))
    parts = [(*empty, astroalign_pairs(P[b], Q[b], float(sigma[b]), gens[b]), 0) for b in range(len(P))]
    return build_from_parts(method="astroalign", P=P, Q=Q, sigma=sigma, log_tau=np.full(len(P), np.nan),
                            tri_p=tri_p, tri_q=tri_q, parts=parts)


#: numpy's own ``default_rng``, which ``_ransac_rng`` puts back.
NUMPY_DEFAULT_RNG = np.random.default_rng
#: Held while ``numpy.random.default_rng`` is replaced: one call at a time, so that no call
#: restores another's replacement.
_RNG_LOCK = threading.Lock()


@contextmanager
def _ransac_rng(rng: np.random.Generator):
    """``numpy.random.default_rng()`` (no seed) returns ``rng`` in this thread, for one call."""
    caller = threading.get_ident()

    def default_rng(seed=None):
        if seed is None and threading.get_ident() == caller:
            return rng
        return NUMPY_DEFAULT_RNG(seed)

    with _RNG_LOCK:
        np.random.default_rng = default_rng
        try:
            yield
        finally:
            np.random.default_rng = NUMPY_DEFAULT_RNG
