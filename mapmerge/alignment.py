"""Closed-form ML alignment of paired landmarks, its covariances and outlier rejection.

For n landmark pairs ``(p_k, q_k)`` with ``q_k = R(θ) µ_k + t + noise`` and
``p_k = µ_k + noise`` (i.i.d. N(0, σ²) per coordinate), the GLRT's closed
form (paper Theorem 1, generalised to n points) gives

    θ* = atan2(-β, -α)        t* = q̄ - R(θ*) p̄        µ*_k = ½ (p_k + R(θ*)ᵀ (q_k - t*))

with ``α = -Σ q̃_k · p̃_k`` and ``β = -Σ p̃_k × q̃_k`` over the centred points,
and the minimum of eq. (5), J* = ½ Σ ‖R(θ*) p_k + t* - q_k‖², which is
σ² χ²(2n - 3) under H1.

``fit_transforms`` solves many independent problems at once (ragged sets
tagged by a trial index, one sum per trial in a fixed order), so one set
alone and the same set in a batch give the same bits; ``align`` is the
batch of one, and ``fit_matched`` the fit of every merge's correspondences.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri

from ._validation import check_points, check_sigma
from .neighbours import njit

#: J = [[0, -1], [1, 0]]: dR/dθ = R J.
ROT90 = np.array([[0.0, -1.0], [1.0, 0.0]])


def wrap_angle(theta):
    """Wrap angles to (-π, π]."""
    wrapped = np.remainder(np.asarray(theta, dtype=float) + np.pi, 2 * np.pi) - np.pi
    return np.where(wrapped <= -np.pi, wrapped + 2 * np.pi, wrapped)


def rotation(theta) -> np.ndarray:
    """The rotation matrix R(θ) = [[cos θ, -sin θ], [sin θ, cos θ]]: (2, 2), or (..., 2, 2) for an array θ."""
    c, s = np.cos(theta), np.sin(theta)
    if np.ndim(theta) == 0:
        return np.array([[c, -s], [s, c]])
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def rotate(theta, x: np.ndarray) -> np.ndarray:
    """R(θ) x for points x (..., n, 2), θ broadcasting over leading axes.

    Elementwise, so a batch of maps rotates to the same bits as each map alone.
    """
    theta = np.asarray(theta, dtype=float)
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    x0, x1 = x[..., 0], x[..., 1]
    first = c * x0
    # Written into one array rather than stacked: called in every EM round, where np.stack's overhead shows.
    out = np.empty(first.shape + (2,), dtype=first.dtype)
    np.subtract(first, s * x1, out=out[..., 0])
    np.add(s * x0, c * x1, out=out[..., 1])
    return out


def covariance_in_p_frame(theta, cov: np.ndarray) -> np.ndarray:
    """Covariances of q landmarks brought into p's frame, ``R(θ)ᵀ Σ R(θ)``.

    ``cov`` (..., n, 2, 2); θ a scalar or one per leading batch index.
    """
    R = rotation(np.asarray(theta, dtype=float))[..., None, :, :]
    return np.swapaxes(R, -1, -2) @ cov @ R


def fit_transforms(trial: np.ndarray, P: np.ndarray, Q: np.ndarray, n_trials: int):
    """θ*, t* and J* of ragged sets of paired points, one set per trial.

    Parameters
    ----------
    trial : (K,) int ndarray
        Set of each pair, in ``0 .. n_trials - 1``.
    P, Q : (K, 2) ndarray
        Paired points.
    n_trials : int

    Returns
    -------
    theta : (n_trials,) ndarray
        NaN for a trial with no pair.
    t : (n_trials, 2) ndarray
    cost : (n_trials,) ndarray
        J*, computed as a residual (no cancellation).
    """
    trial = np.ascontiguousarray(trial, dtype=np.int64)
    P, Q = np.ascontiguousarray(P, dtype=float), np.ascontiguousarray(Q, dtype=float)
    # The sums are compiled; the trigonometry stays numpy's, whose atan2 numba's differs from in the last bit.
    count, bar, dot, cross = _centred_sums(trial, P, Q, int(n_trials))
    theta = np.where(count > 0, wrap_angle(np.arctan2(cross, dot)), np.nan)
    t, cost = _fit_residuals(trial, P, Q, bar, np.cos(theta), np.sin(theta))
    return theta, t, cost


@njit(cache=True, error_model="numpy")
def _centred_sums(trial, P, Q, n_trials):
    """Each set's count, centroids (p̄_x, p̄_y, q̄_x, q̄_y; NaN for an empty set) and Σ q̃·p̃, Σ p̃ x q̃ (-α, -β),
    each summed over the set's pairs in order (the bits of per-set bincounts)."""
    count = np.zeros(n_trials, dtype=np.int64)
    bar = np.zeros((n_trials, 4))
    for k in range(len(trial)):
        b = trial[k]
        count[b] += 1
        bar[b, 0] += P[k, 0]
        bar[b, 1] += P[k, 1]
        bar[b, 2] += Q[k, 0]
        bar[b, 3] += Q[k, 1]
    for b in range(n_trials):
        for c in range(4):
            bar[b, c] /= count[b]
    dot, cross = np.zeros(n_trials), np.zeros(n_trials)
    for k in range(len(trial)):
        b = trial[k]
        px, py, qx, qy = P[k, 0] - bar[b, 0], P[k, 1] - bar[b, 1], Q[k, 0] - bar[b, 2], Q[k, 1] - bar[b, 3]
        dot[b] += qx * px + qy * py
        cross[b] += px * qy - py * qx
    return count, bar, dot, cross


@njit(cache=True)
def _fit_residuals(trial, P, Q, bar, cos, sin):
    """t* = q̄ - R(θ*) p̄ of each set and J*, half its pairs' squared gaps under (θ*, t*) (the optimal µ is
    the midpoint), from ``_centred_sums``' centroids and cos θ*, sin θ*."""
    t, cost = np.empty((len(cos), 2)), np.zeros(len(cos))
    for b in range(len(cos)):
        t[b, 0] = bar[b, 2] - (cos[b] * bar[b, 0] - sin[b] * bar[b, 1])
        t[b, 1] = bar[b, 3] - (sin[b] * bar[b, 0] + cos[b] * bar[b, 1])
    for k in range(len(trial)):
        b = trial[k]
        px, py, qx, qy = P[k, 0] - bar[b, 0], P[k, 1] - bar[b, 1], Q[k, 0] - bar[b, 2], Q[k, 1] - bar[b, 3]
        rx, ry = cos[b] * px - sin[b] * py - qx, sin[b] * px + cos[b] * py - qy
        cost[b] += rx * rx + ry * ry
    return t, 0.5 * cost


def fit_matched(P: np.ndarray, Q: np.ndarray, pair_trial: np.ndarray, pairs: np.ndarray, min_pairs: int):
    """The n-point closed form of every map pair with at least ``min_pairs`` landmark correspondences.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
        The maps.
    pair_trial, pairs : (K,), (K, 2) int ndarray
        Landmark correspondences (p index, q index) and their map pair.
    min_pairs : int
        Fewest correspondences fitted; map pairs with fewer are not matched.

    Returns
    -------
    matched : (B,) bool ndarray
    theta, t, cost : (B,), (B, 2), (B,) ndarray
        θ*, t* and J* (``fit_transforms``) of the matched map pairs, NaN for the others.
    """
    B = len(P)
    matched = np.bincount(pair_trial, minlength=B) >= min_pairs
    use = matched[pair_trial]
    kt, pi, qi = pair_trial[use], pairs[use, 0], pairs[use, 1]
    theta, t, cost = fit_transforms(kt, P[kt, pi], Q[kt, qi], B)
    theta, cost = np.where(matched, theta, np.nan), np.where(matched, cost, np.nan)
    t = np.where(matched[:, None], t, np.nan)
    return matched, theta, t, cost


def paired_transforms(coords_p, coords_q):
    """θ*, t* and J* for row-wise paired point sets of equal size.

    Parameters
    ----------
    coords_p, coords_q : (M, n, 2) ndarray
        ``coords_p[m]`` is paired with ``coords_q[m]`` vertex by vertex.

    Returns
    -------
    theta : (M,) ndarray
    t : (M, 2) ndarray
    cost : (M,) ndarray
    """
    cp = np.asarray(coords_p, dtype=float)
    cq = np.asarray(coords_q, dtype=float)
    M, n = cp.shape[:2]
    if M <= PAIRED_CHUNK:
        return fit_transforms(np.repeat(np.arange(M), n), cp.reshape(-1, 2), cq.reshape(-1, 2), M)
    # Each row's fit is independent of the others (its own sums, in vertex order), so blocks of rows give
    # the same bits while the temporaries, about 40 doubles per point, stay at one block's size: at 10^6
    # landmarks a map pair has 10^7 candidate triangle pairs.
    theta, t, cost = np.empty(M), np.empty((M, 2)), np.empty(M)
    for a in range(0, M, PAIRED_CHUNK):
        b = min(a + PAIRED_CHUNK, M)
        theta[a:b], t[a:b], cost[a:b] = paired_transforms(cp[a:b], cq[a:b])
    return theta, t, cost


#: Rows of ``paired_transforms`` fitted at once.
PAIRED_CHUNK = 1 << 17


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
    def cov(self) -> np.ndarray:
        return transform_covariance(self.mu, self.theta, self.sigma)

    @functools.cached_property
    def mu_cov(self) -> np.ndarray:
        # Only the combined map needs it; the verification stages read cov alone.
        return fused_covariances(self.mu, self.theta, self.sigma, self.cov)

    @classmethod
    def from_fit(cls, theta: float, t: np.ndarray, cost: float, P: np.ndarray, Q: np.ndarray,
                 sigma: float) -> "Alignment":
        """The alignment of fitted (θ*, t*, J*), with µ* from the paired points."""
        mu = 0.5 * (P + rotate(-theta, Q - t))
        return cls(theta=float(theta), t=t, mu=mu, cost=float(cost),
                   log_lr=-float(cost) / (2.0 * sigma**2), dof=2 * P.shape[0] - 3, sigma=sigma)


def transform_covariance(mu: np.ndarray, theta: float, sigma: float) -> np.ndarray:
    """Covariance of (θ, t) for n paired landmarks.

    The Fisher information of eq. (5) in (θ, t, µ) has a 2x2 block 2I/σ² per
    landmark; eliminating µ leaves ``(1/2σ²) [[Σ‖µ‖², bᵀ], [b, n I]]`` for
    (θ, t) with ``b = R J Σµ``.
    """
    b = rotation(theta) @ ROT90 @ mu.sum(axis=0)
    info = np.empty((3, 3))
    info[0, 0] = np.sum(mu**2)
    info[0, 1:] = info[1:, 0] = b
    info[1:, 1:] = mu.shape[0] * np.eye(2)
    return 2.0 * sigma**2 * np.linalg.inv(info)


def fused_covariances(mu: np.ndarray, theta: float, sigma: float, cov: np.ndarray) -> np.ndarray:
    """Covariance (n, 2, 2) of each µ_v, from the inverse Fisher information's µ_v block:
    ``σ²/2 I + ¼ [Jµ_v, Rᵀ] Σ_θt [Jµ_v, Rᵀ]ᵀ`` (``cov`` = Σ_θt, ``transform_covariance``)."""
    n = mu.shape[0]
    G = np.concatenate([(mu @ ROT90.T)[:, :, None], np.broadcast_to(rotation(theta).T, (n, 2, 2))], axis=2)
    return 0.5 * sigma**2 * np.eye(2) + 0.25 * G @ cov @ G.transpose(0, 2, 1)


def mapped_covariance(x: np.ndarray, theta, cov: np.ndarray, own) -> np.ndarray:
    """Covariance (..., m, 2, 2) of q landmarks mapped into p's frame, x = Rᵀ(q - t).

    ``x`` (..., m, 2), ``theta`` (...) and ``cov`` (..., 3, 3), the (θ, t)
    covariance of the transform, carry any leading batch axes (one transform
    per map pair). ``own`` is the landmarks' own noise in q's frame: a
    variance per coordinate broadcasting to (..., m) (a scalar, one per map
    pair as (B, 1), or one per landmark) or full (..., m, 2, 2) covariances.
    """
    theta = np.asarray(theta, dtype=float)
    R_t = np.swapaxes(rotation(theta), -1, -2)[..., None, :, :]
    G = np.concatenate([(-(x @ ROT90.T))[..., None], np.broadcast_to(-R_t, x.shape + (2,))], axis=-1)
    own = np.asarray(own, dtype=float)
    if own.ndim == x.ndim + 1:
        own = covariance_in_p_frame(theta, own)
    else:
        own = np.broadcast_to(own, x.shape[:-1])[..., None, None] * np.eye(2)
    return own + G @ np.asarray(cov)[..., None, :, :] @ np.swapaxes(G, -1, -2)


def prediction_var(points: np.ndarray, alignment: Alignment) -> np.ndarray:
    """Mean per-coordinate variance of R(θ) x + t from the fit's covariance.

    With G = [R J x, I] the Jacobian in (θ, t), ½ tr(G Σ Gᵀ) =
    ½ (‖x‖² Σ_θθ + 2 (R J x)·Σ_θt + tr Σ_tt).
    """
    return prediction_vars(points[None], np.array([alignment.theta]), alignment.cov[None])[0]


def prediction_vars(points: np.ndarray, theta: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``prediction_var`` under F fits at once.

    ``theta`` (F,) and ``cov`` (F, 3, 3) are the fits' rotations and (θ, t)
    covariances; ``points`` (F or 1, ..., 2) are fit f's points in row f (or
    one set for all). Returns (F, ...).
    """
    c, s = np.cos(theta), np.sin(theta)
    # (R J x)·Σ_θt with R J = [[-s, -c], [c, -s]], as one coefficient per coordinate of x.
    a = -s * cov[:, 0, 1] + c * cov[:, 0, 2]
    b = -c * cov[:, 0, 1] - s * cov[:, 0, 2]
    shape = (-1,) + (1,) * (points.ndim - 2)
    a, b, c00, trace_t = (v.reshape(shape) for v in (a, b, cov[:, 0, 0], cov[:, 1, 1] + cov[:, 2, 2]))
    x0, x1 = points[..., 0], points[..., 1]
    return 0.5 * ((x0**2 + x1**2) * c00 + 2 * (x0 * a + x1 * b) + trace_t)


def transform_covariances(trial: np.ndarray, mu: np.ndarray, theta: np.ndarray, sigma, fitted: np.ndarray):
    """``transform_covariance`` of ragged fits at once: (F, 3, 3) for F = ``len(fitted)``.

    ``mu`` (K, 2) are the fused landmarks of every fit, ``trial`` (K,) the
    fit of each; ``theta`` (F,) and ``sigma`` (scalar or (F,)). Fits not
    ``fitted`` get a covariance that is not to be read.
    """
    F = len(fitted)
    c, s = np.cos(theta), np.sin(theta)
    # b = R J Σµ with R J = [[-s, -c], [c, -s]].
    sx, sy = np.bincount(trial, mu[:, 0], F), np.bincount(trial, mu[:, 1], F)
    info = np.zeros((F, 3, 3))
    info[:, 0, 0] = np.bincount(trial, mu[:, 0] ** 2 + mu[:, 1] ** 2, F)
    info[:, 0, 1] = info[:, 1, 0] = -s * sx - c * sy
    info[:, 0, 2] = info[:, 2, 0] = c * sx - s * sy
    info[:, 1, 1] = info[:, 2, 2] = np.bincount(trial, minlength=F)
    info[~fitted] = np.eye(3)  # any invertible matrix
    return 2.0 * np.asarray(sigma, dtype=float).reshape(-1, 1, 1) ** 2 * np.linalg.inv(info)


def fit_alignments(trial: np.ndarray, P: np.ndarray, Q: np.ndarray, sigma, n_trials: int):
    """θ*, t*, µ* and the (θ, t) covariance of ragged sets of paired points, one set per trial.

    ``fit_transforms`` and ``transform_covariances`` in one: ``sigma`` a
    scalar or one per trial. Returns theta (n_trials,), t (n_trials, 2), mu
    (K, 2) and cov (n_trials, 3, 3), the last not to be read for a set of
    fewer than 3 pairs.
    """
    theta, t, _ = fit_transforms(trial, P, Q, n_trials)
    mu = 0.5 * (P + rotate(-theta[trial], (Q - t[trial])[:, None, :])[:, 0])
    cov = transform_covariances(trial, mu, theta, sigma, np.bincount(trial, minlength=n_trials) >= 3)
    return theta, t, mu, cov


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
    return align_pairs(P, Q, check_sigma(sigma))


def align_pairs(P: np.ndarray, Q: np.ndarray, sigma: float) -> Alignment:
    """``align`` without the input checks (for callers holding valid arrays)."""
    theta, t, cost = fit_transforms(np.zeros(len(P), dtype=np.intp), P, Q, 1)
    return Alignment.from_fit(theta[0], t[0], cost[0], P, Q, sigma)


def reject_outliers(P, Q, pairs, sigma, gate_p: float = 1e-3):
    """Iterative fit: drop the worst pair outside the χ²₂ gate and refit (Groth's rule).

    One map pair's ``reject_outliers_batch``: returns the pairs kept.
    """
    keep = reject_outliers_batch(P[None], Q[None], np.zeros(len(pairs), dtype=np.intp), pairs,
                                 np.array([sigma], dtype=float), gate_p)
    return pairs[keep]


def reject_outliers_batch(P, Q, pair_trial, pairs, sigma, gate_p: float = 1e-3) -> np.ndarray:
    """Groth's iterative rejection on B map pairs at once.

    Per map pair: fit the n-point closed form to its pairs, standardise each
    pair's residual by its variance (2σ² plus the fit's prediction variance,
    ``prediction_var``), and while the worst lies outside the χ²₂ gate of
    tail probability ``gate_p`` and three or more pairs remain, drop it
    (the first of equal worst) and refit. Every map pair still rejecting
    takes one round of the same vectorised step.

    Parameters
    ----------
    P, Q : (B, n_p, 2), (B, n_q, 2) ndarray
    pair_trial : (K,) int ndarray
        Map pair of each correspondence.
    pairs : (K, 2) int ndarray
        Correspondences (p index, q index).
    sigma : (B,) ndarray

    Returns
    -------
    keep : (K,) bool ndarray
    """
    gate = chdtri(2, gate_p)
    B = len(P)
    xp, xq = P[pair_trial, pairs[:, 0]], Q[pair_trial, pairs[:, 1]]
    keep = np.ones(len(pairs), dtype=bool)
    rejecting = np.ones(B, dtype=bool)
    while True:
        rejecting &= np.bincount(pair_trial[keep], minlength=B) >= 3
        idx = np.flatnonzero(keep & rejecting[pair_trial])
        if not idx.size:
            return keep
        # Only the F map pairs still rejecting are fitted, numbered 0..F-1 (each one's sums are the same).
        active = np.flatnonzero(rejecting)
        F = len(active)
        k, ak, bk = (np.cumsum(rejecting) - 1)[pair_trial[idx]], xp[idx], xq[idx]
        theta, t, _, cov = fit_alignments(k, ak, bk, sigma[active], F)
        # prediction_var of each p point under its own map pair's fit, then its standardised residual.
        pred = prediction_vars(ak, theta[k], cov[k])
        resid = np.sum((bk - rotate(theta[k], ak[:, None, :])[:, 0] - t[k]) ** 2, axis=1)
        resid /= 2 * sigma[active][k] ** 2 + pred
        # The worst of each map pair, the first of equal worst (a NaN only when all are, and then within the gate).
        worst = np.full(F, -np.inf)
        np.fmax.at(worst, k, resid)
        hit = np.flatnonzero(resid == worst[k])
        first = np.full(F, len(k))
        np.minimum.at(first, k[hit], hit)
        found = first < len(k)
        out = np.zeros(F, dtype=bool)
        out[found] = resid[first[found]] > gate
        keep[idx[first[out]]] = False
        rejecting[active[~out]] = False
