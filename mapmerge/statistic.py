"""Closed-form GLRT between triangles and n-point ML alignment (paper Theorem 1).

Model (paper eq. 2, DESIGN §2): map q sees map p's landmarks through a rigid
motion, ``q_v = R(θ) µ_v + t + noise`` and ``p_v = µ_v + noise``, all noise
i.i.d. N(0, σ²) per coordinate. With centred vertices ``p̃_v = p_v - p̄`` and
``q̃_v = q_v - q̄`` (the paper's ``Q⁻ y``):

    α = -Σ_v q̃_v · p̃_v          β = -Σ_v p̃_v × q̃_v      (a × b = a_x b_y - a_y b_x)
    γ = ½ (Σ ‖p̃_v‖² + Σ ‖q̃_v‖²)
    θ* = atan2(-β, -α)           t* = q̄ - R(θ*) p̄
    µ*_v = ½ (p_v + R(θ*)ᵀ (q_v - t*))
    J* = γ - √(α² + β²)          log Λ = -J* / (2σ²)

The paper writes θ* = sgn(β)[cos⁻¹(α/√(α²+β²)) - π], which is wrong when
β = 0 and θ* = π; atan2 is right everywhere. Under H1, J*/σ² is χ² with
2n - 3 degrees of freedom (3 for a triangle).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ._validation import check_points, check_sigma


def wrap_angle(theta):
    """Wrap angles to (-π, π]."""
    wrapped = np.remainder(np.asarray(theta, dtype=float) + np.pi, 2 * np.pi) - np.pi
    return np.where(wrapped <= -np.pi, wrapped + 2 * np.pi, wrapped)


def rotation(theta: float) -> np.ndarray:
    """The 2x2 rotation matrix R(θ) = [[cos θ, -sin θ], [sin θ, cos θ]]."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


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
    cost, _ = pairwise_cost(cp, cq, cyclic)
    return -cost / (2.0 * sigma**2)


def ccw_order(coords: np.ndarray) -> np.ndarray:
    """Permutation (T, 3) putting each triangle's vertices counter-clockwise."""
    d1, d2 = coords[:, 1] - coords[:, 0], coords[:, 2] - coords[:, 0]
    clockwise = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] < 0
    return np.where(clockwise[:, None], [0, 2, 1], [0, 1, 2])


def pairwise_cost(cp: np.ndarray, cq: np.ndarray, cyclic: bool = False):
    """Minimum cost J* (Tp, Tq) of every triangle pair, as matrix products.

    With ``cyclic``, ``cp`` and ``cq`` must already be counter-clockwise
    (``ccw_order``) for the shifts to cover every orientation-preserving
    correspondence.

    Returns
    -------
    cost : (Tp, Tq) ndarray
    shift : (Tp, Tq) int8 ndarray
        The cyclic shift ``s`` of q's vertices that attains it (q vertex
        ``(v + s) % 3`` pairs with p vertex ``v``); all zero unless ``cyclic``.
    """
    return _min_cost(cp, cq, cyclic, pairwise=True)


def _min_cost(cp, cq, cyclic: bool, pairwise: bool):
    """J* = γ - max over the allowed vertex shifts of √(α² + β²).

    ``pairwise``: every p triangle against every q triangle; otherwise row m
    of ``cp`` against row m of ``cq``. Leading batch axes broadcast (many
    independent map pairs at once). Elementwise products rather than matrix
    products, so a pair's value never depends on what else is in the batch.
    """
    pc = cp - cp.mean(axis=-2, keepdims=True)
    qc = cq - cq.mean(axis=-2, keepdims=True)
    sp, sq = (pc**2).sum(axis=(-2, -1)), (qc**2).sum(axis=(-2, -1))
    # As complex numbers, conj(p̃_v)·q̃_v = -(α_v + iβ_v): one product per vertex.
    zp, zq = np.empty(pc.shape[:-1], complex), np.empty(qc.shape[:-1], complex)
    zp.real, zp.imag, zq.real, zq.imag = pc[..., 0], -pc[..., 1], qc[..., 0], qc[..., 1]
    if pairwise:  # (..., Tp, 1, 3) against (..., 1, Tq, 3)
        zp, sp = zp[..., :, None, :], sp[..., :, None]
        zq, sq = zq[..., None, :, :], sq[..., None, :]
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
            best = np.where(better, r, best)
            shift[better] = s
    # γ - r loses digits when the pair is nearly congruent; J* >= 0 exactly.
    return np.maximum(gamma - best, 0.0), shift


def paired_transforms(coords_p, coords_q):
    """θ*, t* and J* for row-wise paired point sets.

    Parameters
    ----------
    coords_p, coords_q : (M, n, 2) ndarray
        ``coords_p[m]`` is paired with ``coords_q[m]`` vertex by vertex.

    Returns
    -------
    theta : (M,) ndarray
    t : (M, 2) ndarray
    cost : (M,) ndarray
        The minimum of eq. (5), computed as a residual (no cancellation).
    """
    cp = np.asarray(coords_p, dtype=float)
    cq = np.asarray(coords_q, dtype=float)
    p_bar = cp.mean(axis=1)
    q_bar = cq.mean(axis=1)
    px, py = (cp - p_bar[:, None, :]).transpose(2, 0, 1)
    qx, qy = (cq - q_bar[:, None, :]).transpose(2, 0, 1)
    alpha = -(qx * px + qy * py).sum(axis=1)
    beta = -(px * qy - py * qx).sum(axis=1)
    theta = wrap_angle(np.arctan2(-beta, -alpha))
    c, s = np.cos(theta), np.sin(theta)
    t = q_bar - np.stack([c * p_bar[:, 0] - s * p_bar[:, 1], s * p_bar[:, 0] + c * p_bar[:, 1]], axis=1)
    rx = c[:, None] * px - s[:, None] * py - qx
    ry = s[:, None] * px + c[:, None] * py - qy
    # Optimal µ is the midpoint, so each vertex leaves half its squared gap.
    cost = 0.5 * (rx**2 + ry**2).sum(axis=1)
    return theta, t, cost


def paired_cost(cp: np.ndarray, cq: np.ndarray, cyclic: bool = False):
    """J* of row-paired triangles, and the best cyclic shift of q (see pairwise_cost)."""
    return _min_cost(cp, cq, cyclic, pairwise=False)


@dataclass(frozen=True)
class Alignment:
    """ML alignment of paired landmarks (Theorem 1 for n points).

    Attributes
    ----------
    theta : float
        Rotation θ* of map q relative to map p, in (-π, π].
    t : (2,) ndarray
        Translation t*, so that ``q ≈ R(θ*) p + t*``.
    mu : (n, 2) ndarray
        ML landmark positions µ* in map p's frame.
    cost : float
        Minimum of eq. (5), J* >= 0.
    log_lr : float
        ``-J* / (2σ²)``.
    dof : int
        ``2n - 3``: degrees of freedom of ``J*/σ²`` under H1.
    sigma : float
    cov : (3, 3) ndarray
        Covariance of ``(θ*, t*_x, t*_y)``: inverse Fisher information with
        the landmarks µ profiled out (Cramér-Rao bound, evaluated at µ*).
        Computed on first use.
    mu_cov : (n, 2, 2) ndarray
        Covariance of each fused landmark µ*_v (computed on first use).
    """

    theta: float
    t: np.ndarray
    mu: np.ndarray
    cost: float
    log_lr: float
    dof: int
    sigma: float

    @functools.cached_property
    def _covariances(self):
        return transform_covariance(self.mu, self.theta, self.sigma)

    @property
    def cov(self) -> np.ndarray:
        return self._covariances[0]

    @property
    def mu_cov(self) -> np.ndarray:
        return self._covariances[1]


#: J = [[0, -1], [1, 0]]: dR/dθ = R J.
_J = np.array([[0.0, -1.0], [1.0, 0.0]])


def transform_covariance(mu: np.ndarray, theta: float, sigma: float):
    """Covariance of (θ, t) and of each µ_v for n paired landmarks.

    The Fisher information of eq. (5) in (θ, t, µ) has a 2x2 block 2I/σ² per
    landmark; eliminating µ leaves ``(1/2σ²) [[Σ‖µ‖², bᵀ], [b, n I]]`` for
    (θ, t) with ``b = R J Σµ``. The µ_v block of the inverse is
    ``σ²/2 I + ¼ [Jµ_v, Rᵀ] Σ_θt [Jµ_v, Rᵀ]ᵀ``.
    """
    R = rotation(theta)
    n = mu.shape[0]
    b = R @ _J @ mu.sum(axis=0)
    info = np.empty((3, 3))
    info[0, 0] = np.sum(mu**2)
    info[0, 1:] = info[1:, 0] = b
    info[1:, 1:] = n * np.eye(2)
    cov = 2.0 * sigma**2 * np.linalg.inv(info)
    G = np.concatenate([(mu @ _J.T)[:, :, None], np.broadcast_to(R.T, (n, 2, 2))], axis=2)
    mu_cov = 0.5 * sigma**2 * np.eye(2) + 0.25 * G @ cov @ G.transpose(0, 2, 1)
    return cov, mu_cov


def mapped_covariance(x: np.ndarray, theta: float, cov: np.ndarray, var) -> np.ndarray:
    """Covariance (m, 2, 2) of q landmarks mapped into p's frame, x = Rᵀ(q - t).

    ``var`` is the landmarks' own variance per coordinate (a scalar, or one
    per landmark); ``cov`` the (θ, t) covariance of the transform.
    """
    G = np.concatenate([(-(x @ _J.T))[:, :, None], np.broadcast_to(-rotation(theta).T, (x.shape[0], 2, 2))], axis=2)
    own = np.broadcast_to(np.asarray(var, dtype=float), (x.shape[0],))[:, None, None] * np.eye(2)
    return own + G @ cov @ G.transpose(0, 2, 1)


def align(P, Q, sigma=1.0) -> Alignment:
    """Closed-form ML rotation, translation and landmarks for paired points.

    Parameters
    ----------
    P, Q : (n, 2) array_like
        Row k of ``P`` and row k of ``Q`` are the same landmark seen in map p
        and map q; n >= 2.
    sigma : float, default 1.0
        Per-coordinate noise standard deviation, > 0 (scales ``log_lr`` only).

    Returns
    -------
    Alignment

    Raises
    ------
    ValueError
        On NaN/inf, wrong or mismatched shapes, n < 2 or ``sigma <= 0``.
    """
    P = check_points(P, "P", min_points=2, geometry=False)
    Q = check_points(Q, "Q", min_points=2, geometry=False)
    if P.shape != Q.shape:
        raise ValueError(f"P and Q must have the same shape, got {P.shape} and {Q.shape}")
    sigma = check_sigma(sigma)
    return _align(P, Q, sigma)


def _align(P: np.ndarray, Q: np.ndarray, sigma: float) -> Alignment:
    theta, t, cost = paired_transforms(P[None], Q[None])
    theta, t, cost = float(theta[0]), t[0], float(cost[0])
    rot = rotation(theta)
    mu = 0.5 * (P + (Q - t) @ rot)  # (Q - t) @ R = rows of Rᵀ (q - t)
    return Alignment(
        theta=theta,
        t=t,
        mu=mu,
        cost=cost,
        log_lr=-cost / (2.0 * sigma**2),
        dof=2 * P.shape[0] - 3,
        sigma=sigma,
    )


def _check_triangles(coords, name: str) -> np.ndarray:
    try:
        arr = np.asarray(coords, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (T, 3, 2) array of numbers") from None
    if arr.ndim != 3 or arr.shape[1:] != (3, 2):
        raise ValueError(f"{name} must have shape (T, 3, 2), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; all coordinates must be finite")
    return arr
