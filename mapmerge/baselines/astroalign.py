"""astroalign's ``find_transform`` as a baseline (optional extra ``[baselines]``).

The two point lists are handed to ``astroalign.find_transform`` with the
coordinates scaled so that its pixel tolerance equals
``ASTROALIGN_TOL_SIGMAS`` σ. astroalign raises when it finds no transform:
that is reported as "no match"; a wrong transform is kept and shows up in
the errors.

Its RANSAC shuffles candidates with ``numpy.random.default_rng()`` and
offers no seed argument. So that the baseline is reproducible, the
``default_rng`` astroalign sees returns the caller's generator for the
duration of the call (and only then); nothing global is seeded. The swap is
seen by the whole process, so calls from several threads take turns. Without a
generator, one seeded by the two maps' bytes is used, so the same maps give
the same answer.
"""

from __future__ import annotations

import hashlib
import threading
from contextlib import contextmanager

import numpy as np

from ..result import MergeBatch, build_from_parts
from ..triangles import TriangleBatch

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
        with _ransac_rng(astroalign, rng):
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
    gens = ([np.random.default_rng(rng)] * len(P) if rng is not None else
            [np.random.default_rng(np.frombuffer(hashlib.sha256(P[b].tobytes() + Q[b].tobytes()).digest(),
                                                 dtype=np.uint32)) for b in range(len(P))])
    empty = (np.empty((0, 2), dtype=np.intp), np.empty(0), np.empty(0, bool))
    parts = [(*empty, astroalign_pairs(P[b], Q[b], float(sigma[b]), gens[b]), 0) for b in range(len(P))]
    return build_from_parts(method="astroalign", P=P, Q=Q, sigma=sigma, log_tau=np.full(len(P), np.nan),
                            tri_p=tri_p, tri_q=tri_q, parts=parts)


#: Held while astroalign sees a swapped numpy: one call at a time, so that no
#: call draws from another's generator or restores another's swap.
_SWAP_LOCK = threading.Lock()


@contextmanager
def _ransac_rng(astroalign, rng: np.random.Generator):
    """astroalign's view of numpy, whose ``random.default_rng()`` returns ``rng``, for one call."""
    with _SWAP_LOCK:
        seen = astroalign._np
        astroalign._np = _SeededNumpy(rng)
        try:
            yield
        finally:
            astroalign._np = seen


class _SeededNumpy:
    def __init__(self, rng: np.random.Generator):
        self.random = _SeededRandom(rng)

    def __getattr__(self, name):
        return getattr(np, name)


class _SeededRandom:
    def __init__(self, rng: np.random.Generator):
        self._rng = rng

    def default_rng(self, seed=None):
        return self._rng if seed is None else np.random.default_rng(seed)

    def __getattr__(self, name):
        return getattr(np.random, name)
