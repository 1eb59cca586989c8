"""Closed-form GLRT between triangles (paper Theorem 1).

Model (paper eq. 2): map q sees map p's landmarks through a rigid motion,
``q_v = R(θ) µ_v + t + noise`` and ``p_v = µ_v + noise``, all noise i.i.d.
N(0, σ²) per coordinate. With centred vertices ``p̃_v = p_v - p̄`` and
``q̃_v = q_v - q̄`` (the paper's ``Q⁻ y``):

    α = -Σ_v q̃_v · p̃_v          β = -Σ_v p̃_v × q̃_v      (a × b = a_x b_y - a_y b_x)
    γ = ½ (Σ ‖p̃_v‖² + Σ ‖q̃_v‖²)
    θ* = atan2(-β, -α)           t* = q̄ - R(θ*) p̄
    J* = γ - √(α² + β²)          log Λ = -J* / (2σ²)

The paper writes θ* = sgn(β)[cos⁻¹(α/√(α²+β²)) - π], which is wrong when
β = 0 and θ* = π; atan2 is right everywhere (``mapmerge.alignment``). Under
H1, J*/σ² is χ² with 2n - 3 degrees of freedom (3 for a triangle).

Every value is elementwise in the triangle pair, so a pair's score never
depends on the batch it was computed in.
"""

from __future__ import annotations

import numpy as np

from ._validation import check_finite, check_sigma, float_array
from .triangles import TriangleBatch, ccw_order, centroids

#: Triangle pairs scored per numpy call by ``pairwise_log_lr_blocks`` and ``min_cost``'s listed pairs: small enough
#: that the temporaries stay in cache (64 maps of 20 landmarks; one big map).
BLOCK_PAIRS = 2**16


def glrt(coords_p, coords_q, sigma, cyclic: bool = False) -> np.ndarray:
    """Log generalized likelihood ratios between every pair of triangles.

    Parameters
    ----------
    coords_p : (Tp, 3, 2) array_like
        Triangles of map p in Groth order (``Triangles.coords``).
    coords_q : (Tq, 3, 2) array_like
        Triangles of map q in Groth order.
    sigma : float
        Known per-coordinate noise standard deviation, > 0.
    cyclic : bool, default False
        Order-robust statistic: both triangles are put in counter-clockwise
        order and the best of the three cyclic orders of q is taken, i.e. the
        best of every orientation-preserving vertex correspondence. A Groth
        order flip of a near-isosceles triangle swaps two vertices (it
        reverses orientation), so cyclic shifts of the Groth order alone
        would not undo it; after CCW normalisation they do.

    Returns
    -------
    (Tp, Tq) ndarray
        ``log Λ = -J* / (2σ²) <= 0`` for every pair.

    Raises
    ------
    ValueError
        On wrong shapes, non-finite coordinates or ``sigma <= 0``.
    """
    cp = _check_triangles(coords_p, "coords_p")
    cq = _check_triangles(coords_q, "coords_q")
    sigma = check_sigma(sigma)
    if cyclic:
        cp = np.take_along_axis(cp, ccw_order(cp)[..., None], axis=1)
        cq = np.take_along_axis(cq, ccw_order(cq)[..., None], axis=1)
    cost, _ = min_cost(cp, cq, cyclic)
    return log_lr_from_cost(cost, sigma)


def log_lr_from_cost(cost, sigma):
    """``log Λ = -J* / (2σ²)``; 2σ² formed from a Python float so that every
    path (one pair, a batch) gives the same bits."""
    two_var = 2.0 * np.array([float(s) ** 2 for s in np.ravel(sigma)]).reshape(np.shape(sigma))
    return cost / -two_var


def min_cost(cp, cq, cyclic: bool = False, pairs=None):
    """Minimum cost J* = γ - max over the allowed vertex shifts of √(α² + β²).

    Parameters
    ----------
    cp, cq : (..., Tp, 3, 2), (..., Tq, 3, 2) ndarray
        Triangles; with ``cyclic`` both counter-clockwise (``ccw_order``) so
        that the cyclic shifts cover every orientation-preserving
        correspondence. Leading batch axes broadcast.
    cyclic : bool
        Best of the three cyclic shifts of q's vertices.
    pairs : (i, j) of two (M,) int ndarrays, optional
        Only triangle ``i[m]`` of (Tp, 3, 2) ``cp`` against triangle ``j[m]``
        of (Tq, 3, 2) ``cq``, each triangle centred once however many pairs
        it is in (the bits of the same pairs in the full matrix); default:
        every p triangle against every q triangle.

    Returns
    -------
    cost : ndarray
        (..., Tp, Tq), or (M,) for ``pairs``.
    shift : int8 ndarray, same shape
        The cyclic shift ``s`` of q's vertices that attains it (q vertex
        ``(v + s) % 3`` pairs with p vertex ``v``); zero unless ``cyclic``.
    """
    # As complex numbers, conj(p̃_v)·q̃_v = -(α_v + iβ_v): one product per vertex.
    zp, sp = _centred(cp, conjugate=True)
    zq, sq = _centred(cq)
    if pairs is None:  # (..., Tp, 1, 3) against (..., 1, Tq, 3)
        return _min_over_shifts(zp[..., :, None, :], sp[..., :, None], zq[..., None, :, :], sq[..., None, :], cyclic)
    # Gathered a block at a time, so that the temporaries stay in cache.
    i, j = pairs
    parts = [_min_over_shifts(zp[i[a:a + BLOCK_PAIRS]], sp[i[a:a + BLOCK_PAIRS]], zq[j[a:a + BLOCK_PAIRS]],
                              sq[j[a:a + BLOCK_PAIRS]], cyclic) for a in range(0, max(len(i), 1), BLOCK_PAIRS)]
    return np.concatenate([c for c, _ in parts]), np.concatenate([s for _, s in parts])


def _min_over_shifts(zp, sp, zq, sq, cyclic: bool):
    """``min_cost`` of centred triangles (``_centred``) paired elementwise, broadcasting."""
    gamma = 0.5 * (sp + sq)
    best, shift = None, None
    for s in range(3 if cyclic else 1):
        # Summed vertex by vertex: three broadcast products beat a reduction
        # over a length-3 axis by far.
        w = zp[..., 0] * zq[..., s]
        w += zp[..., 1] * zq[..., (1 + s) % 3]
        w += zp[..., 2] * zq[..., (2 + s) % 3]
        r = np.abs(w)  # √(α² + β²)
        if best is None:
            best, shift = r, np.zeros(r.shape, dtype=np.int8)
        else:
            better = r > best
            np.maximum(best, r, out=best)  # r where better; equal values are the same bits
            shift[better] = s
    # γ - r loses digits when the pair is nearly congruent; J* >= 0 exactly.
    return np.maximum(gamma - best, 0.0), shift


def _centred(c, conjugate: bool = False):
    """Each triangle's vertices about their centroid as complex numbers (conjugated for p), and Σ ‖c̃_v‖²."""
    centred = c - centroids(c)[..., None, :]
    z = np.empty(centred.shape[:-1], complex)
    z.real, z.imag = centred[..., 0], -centred[..., 1] if conjugate else centred[..., 1]
    return z, (centred**2).sum(axis=(-2, -1))


def pairwise_log_lr_blocks(tri_p: TriangleBatch, tri_q: TriangleBatch, vp: np.ndarray, vq: np.ndarray,
                           sigma: np.ndarray, cyclic: bool = False):
    """log Λ of every triangle pair of every map pair of a batch, a block of map pairs at a time.

    Parameters
    ----------
    tri_p, tri_q : TriangleBatch
        Triangles of the B maps p and the B maps q.
    vp, vq : (Sp, 3), (Sq, 3) int ndarray
        Their vertices in the statistic's order (Groth, or counter-clockwise
        for ``cyclic``).
    sigma : (B,) ndarray
    cyclic : bool

    Yields
    ------
    trials : (b,) int ndarray
        The block's map pairs.
    log_lr : (b, tp, tq) ndarray
        Entry ``[k, i, j]`` is triangle i of map p ``trials[k]`` against
        triangle j of its map q, for i and j below the map's own triangle
        counts; entries past them are padding, not scores.
    shift : (b, tp, tq) int8 ndarray

    Map pairs go in blocks of about ``BLOCK_PAIRS`` triangle pairs, grouped by
    triangle count so that each block is padded only to its own largest
    map; values are elementwise, so neither changes them.
    """
    pad_p, pad_q = tri_p.padded(vp), tri_q.padded(vq)
    count_p, count_q = tri_p.count, tri_q.count
    block = max(1, BLOCK_PAIRS // max(pad_p.shape[1] * pad_q.shape[1], 1))
    flat_p, flat_q = tri_p.maps.reshape(-1, 2), tri_q.maps.reshape(-1, 2)
    n_p, n_q = tri_p.maps.shape[1], tri_q.maps.shape[1]
    order = np.lexsort((count_q, count_p))
    for a in range(0, len(tri_p), block):
        trials = order[a:a + block]
        tp, tq = count_p[trials].max(), count_q[trials].max()
        cp = flat_p[trials[:, None, None] * n_p + pad_p[trials, :tp]]
        cq = flat_q[trials[:, None, None] * n_q + pad_q[trials, :tq]]
        cost, shift = min_cost(cp, cq, cyclic)
        yield trials, log_lr_from_cost(cost, sigma[trials][:, None, None]), shift


def _check_triangles(coords, name: str) -> np.ndarray:
    arr = float_array(coords, f"{name} must be a (T, 3, 2) array of real numbers")
    if arr.ndim != 3 or arr.shape[1:] != (3, 2):
        raise ValueError(f"{name} must have shape (T, 3, 2), got {arr.shape}")
    check_finite(arr, name)
    return arr
