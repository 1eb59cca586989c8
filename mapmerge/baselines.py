"""Outside baselines run through the same interface: Groth's voting and astroalign.

``groth_merge``: Groth (1986)'s star-pattern matcher on the Delaunay
triangles (Groth used every triple of the brightest stars; Delaunay keeps
it linear). Each triangle gets the rotation/translation/scale invariants
R = r3/r2 (longest over shortest side) and C = cos of the angle at vertex 1,
with Groth's tolerances for a vertex position error ε; pairs whose
invariants agree within the tolerances and whose orientation agrees are
matched, every match votes for its three vertex correspondences, the
correspondences with at least two votes are accepted one-to-one in
decreasing vote order, and the transform is fitted with the n-point closed
form, dropping the worst correspondence outside a χ²₂ gate and refitting
until none is left outside (Groth's iterative rejection).

``astroalign_merge``: ``astroalign.find_transform`` (optional dependency,
``pip install mapmerge[baselines]``) on the two point lists, coordinates
scaled so that its pixel tolerance equals ``ASTROALIGN_TOL_SIGMAS`` σ.
astroalign raises when it finds no transform: that is reported as "no
match"; a wrong transform is kept and shows up in the errors. Its RANSAC
draws from an unseeded ``np.random.default_rng()``; here it draws from a
generator seeded by the two maps' bytes instead, so the baseline gives the
same answer every time it sees the same maps (nothing global is seeded).
"""

from __future__ import annotations

import hashlib

import numpy as np

from .matching import correspondences
from .merging import finish
from .statistic import paired_transforms
from .verification import reject_outliers
from .triangles import _triangulate

#: Groth's ε, the position tolerance of a vertex, in units of σ.
GROTH_EPS_SIGMAS = 3.0
#: Groth's limit on the side ratio R: longer triangles are too unstable.
GROTH_MAX_RATIO = 10.0
#: Outlier gate on the fitted correspondences (χ²₂ tail probability).
GROTH_GATE_P = 1e-3
#: astroalign's pixel tolerance (astroalign.PIXEL_TOL) is set to this many σ.
ASTROALIGN_TOL_SIGMAS = 3.0


def _groth_invariants(coords, eps):
    v1, v2, v3 = coords[:, 0], coords[:, 1], coords[:, 2]
    a, b = v2 - v1, v3 - v1
    r2 = np.linalg.norm(a, axis=1)  # shortest side, v1-v2
    r3 = np.linalg.norm(b, axis=1)  # longest side, v3-v1
    R = r3 / r2
    C = np.sum(a * b, axis=1) / (r2 * r3)
    F = eps**2 * (1 / r3**2 - C / (r3 * r2) + 1 / r2**2)
    tR2 = 2 * R**2 * F
    tC2 = 2 * (1 - C**2) * F + 3 * C**2 * F**2
    sense = np.sign(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    return R, C, tR2, tC2, sense


def groth_merge(P, Q, sigma):
    """Groth's invariant matching with voting (inputs already valid)."""
    tri_p, tri_q = _triangulate(P), _triangulate(Q)
    eps = GROTH_EPS_SIGMAS * sigma
    Rp, Cp, tRp, tCp, sp = _groth_invariants(tri_p.coords, eps)
    Rq, Cq, tRq, tCq, sq = _groth_invariants(tri_q.coords, eps)
    ok = (
        ((Rp[:, None] - Rq[None]) ** 2 < tRp[:, None] + tRq[None])
        & ((Cp[:, None] - Cq[None]) ** 2 < tCp[:, None] + tCq[None])
        & (sp[:, None] == sq[None])
        & (Rp[:, None] < GROTH_MAX_RATIO)
        & (Rq[None] < GROTH_MAX_RATIO)
    )
    tri_pairs = np.argwhere(ok).astype(np.intp)
    vp, vq = tri_p.vertices[tri_pairs[:, 0]], tri_q.vertices[tri_pairs[:, 1]]
    _, _, cost = paired_transforms(P[vp], Q[vq])
    scores = -cost / (2 * sigma**2)
    pairs, n_conflicts = _vote(vp, vq)
    pairs = reject_outliers(P, Q, pairs, sigma, GROTH_GATE_P)
    to_q = np.full(P.shape[0], -1)
    to_q[pairs[:, 0]] = pairs[:, 1]
    declared = np.all(to_q[vp] == vq, axis=1)
    return finish(P, Q, sigma, pairs, n_conflicts, tri_pairs, scores, declared, np.nan,
                  tri_p, tri_q, "groth")


def _vote(vp, vq):
    """One-to-one correspondences by decreasing votes, at least two votes each."""
    pairs, conflicts = correspondences(vp, vq, np.ones(len(vp)))
    if pairs.shape[0] == 0:
        return pairs, conflicts
    n = int(max(vp.max(), vq.max())) + 1
    keys, votes = np.unique(vp.ravel() * n + vq.ravel(), return_counts=True)
    v = votes[np.searchsorted(keys, pairs[:, 0] * n + pairs[:, 1])]
    return pairs[v >= 2], conflicts


def astroalign_merge(P, Q, sigma):
    """astroalign's ``find_transform`` as a baseline (inputs already valid)."""
    try:
        import astroalign
    except ImportError as exc:  # optional extra
        raise ImportError("method='astroalign' needs the optional package: pip install 'mapmerge[baselines]'") from exc
    scale = astroalign.PIXEL_TOL / (ASTROALIGN_TOL_SIGMAS * sigma)
    tri_p, tri_q = _triangulate(P), _triangulate(Q)
    empty = np.empty((0, 2), dtype=np.intp)
    seed = np.frombuffer(hashlib.sha256(P.tobytes() + Q.tobytes()).digest(), dtype=np.uint32)
    numpy_seen_by_astroalign = astroalign._np
    astroalign._np = _SeededNumpy(np.random.default_rng(seed))
    try:
        _, (src, dst) = astroalign.find_transform(
            P * scale, Q * scale, max_control_points=max(len(P), len(Q))
        )
    except (astroalign.MaxIterError, ValueError):
        pairs = empty
    else:
        # astroalign returns matched coordinates; recover the landmark indices.
        ip = np.argmin(np.linalg.norm(P[None] * scale - src[:, None], axis=2), axis=1)
        iq = np.argmin(np.linalg.norm(Q[None] * scale - dst[:, None], axis=2), axis=1)
        # Keep the first match of every landmark so the pairs are one-to-one.
        first = np.zeros(len(ip), bool)
        first[np.unique(ip, return_index=True)[1]] = True
        first &= np.isin(np.arange(len(iq)), np.unique(iq, return_index=True)[1])
        pairs = np.stack([ip[first], iq[first]], axis=1).astype(np.intp)
    finally:
        astroalign._np = numpy_seen_by_astroalign
    return finish(P, Q, sigma, pairs, 0, empty, np.empty(0), np.empty(0, bool), np.nan,
                  tri_p, tri_q, "astroalign")


class _SeededNumpy:
    """numpy as astroalign's module sees it, except that ``random.default_rng()``
    returns the given generator."""

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


BASELINES = {"groth": groth_merge, "astroalign": astroalign_merge}
