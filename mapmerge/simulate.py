"""Synthetic pairs of overlapping landmark maps with ground truth (DESIGN §4).

Two robots explore neighbouring rectangles of a world with landmarks at unit
density. Map p covers ``[0, w] x [0, h]``; map q covers the same-size
rectangle shifted right so that the shared strip holds ``c = round(overlap·n)``
of each map's ``n`` landmarks. Exactly ``c`` landmarks are drawn uniformly in
the strip and ``n - c`` in each map's own part, so every trial has the stated
overlap. Map q's frame is the world seen through a uniform random rotation
and a random translation, ``q = R(θ) x + t``; both maps then get independent
N(0, σ²) noise per coordinate, with σ set from the SNR:

    SNR_dB = 10 log10(σ̄² / (2σ²)),

σ̄² the sample variance of the edge lengths of the Delaunay graph of all true
landmarks. Row order of each map is shuffled so indices carry no truth.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from scipy.spatial import Delaunay

#: Width / height of each map's rectangle.
DEFAULT_ASPECT = 1.0


@dataclass(frozen=True)
class Scenario:
    """One synthetic map pair and its ground truth.

    Attributes
    ----------
    p, q : (n, 2) ndarray
        Noisy landmark maps, each in its own frame.
    ids_p, ids_q : (n,) int ndarray
        True landmark id of each row; equal ids are the same landmark.
    truth : (L, 2) ndarray
        True position of landmark id k in map p's (world) frame.
    sigma : float
        Per-coordinate noise standard deviation.
    theta : float
        True rotation of q's frame, ``q ≈ R(θ) p + t``.
    t : (2,) ndarray
        True translation.
    snr_db : float
    sigma_bar2 : float
        Sample variance of the true Delaunay edge lengths.
    """

    p: np.ndarray
    q: np.ndarray
    ids_p: np.ndarray
    ids_q: np.ndarray
    truth: np.ndarray
    sigma: float
    theta: float
    t: np.ndarray
    snr_db: float
    sigma_bar2: float

    @functools.cached_property
    def n_common(self) -> int:
        return int(np.intersect1d(self.ids_p, self.ids_q).size)


def sigma_from_snr(points: np.ndarray, snr_db: float) -> tuple[float, float]:
    """σ for a given SNR on the true landmarks; returns ``(sigma, sigma_bar2)``."""
    sigma, sigma_bar2 = sigmas_from_snr(points[None], snr_db)
    return float(sigma[0]), float(sigma_bar2[0])


def sigmas_from_snr(worlds: np.ndarray, snr_db: float) -> tuple[np.ndarray, np.ndarray]:
    """``sigma_from_snr`` for B point sets (B, L, 2) at once: (B,) σ and σ̄²."""
    sigma_bar2 = edge_length_variance(worlds, [Delaunay(pts) for pts in worlds])
    return np.sqrt(sigma_bar2 / (2.0 * 10.0 ** (snr_db / 10.0))), sigma_bar2


def edge_length_variance(worlds: np.ndarray, triangulations) -> np.ndarray:
    """Sample variance σ̄² of the Delaunay edge lengths of each of B point sets.

    Parameters
    ----------
    worlds : (B, L, 2) ndarray
    triangulations : sequence of B ``scipy.spatial.Delaunay``
        One per point set.

    Returns
    -------
    (B,) ndarray
        Each value depends on its own point set only (sums in edge order),
        so one set alone and the same set in a batch give the same bits.
    """
    simplices = np.concatenate([tri.simplices for tri in triangulations])
    neighbors = np.concatenate([tri.neighbors for tri in triangulations])
    count = [len(tri.simplices) for tri in triangulations]
    first = np.repeat(np.cumsum(count) - count, count)
    # The edge opposite vertex v of simplex s is shared with neighbors[s, v];
    # the lower-numbered simplex of the pair (or a boundary one) owns it.
    own = (neighbors == -1) | (neighbors + first[:, None] > np.arange(len(simplices))[:, None])
    s, v = np.nonzero(own)
    trial = np.repeat(np.arange(len(count)), count)[s]
    B, L = worlds.shape[:2]
    # Flat indices: one gather per edge end instead of a 2-D fancy index.
    flat = simplices.ravel()
    first_end = trial * L + flat[3 * s + (v + 1) % 3]
    second_end = trial * L + flat[3 * s + (v + 2) % 3]
    xs, ys = worlds[..., 0].ravel(), worlds[..., 1].ravel()
    dx, dy = xs[first_end] - xs[second_end], ys[first_end] - ys[second_end]
    length = np.sqrt(dx**2 + dy**2)
    n_edges = np.bincount(trial, minlength=B)
    mean = np.bincount(trial, length, B) / n_edges
    return np.bincount(trial, (length - mean[trial]) ** 2, B) / (n_edges - 1)


def rotate(theta, x: np.ndarray) -> np.ndarray:
    """R(θ) x for points x (..., n, 2), θ broadcasting over leading axes.

    Elementwise, so a batch of maps rotates to the same bits as each map alone.
    """
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    return np.stack([c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1]], axis=-1)


def make_pair(
    n_landmarks: int = 100,
    overlap: float = 0.75,
    snr_db: float = 40.0,
    rng=None,
    aspect: float = DEFAULT_ASPECT,
    unrelated: bool = False,
) -> Scenario:
    """Draw one overlapping map pair (DESIGN §4).

    Parameters
    ----------
    n_landmarks : int, default 100
        Landmarks per map, >= 3.
    overlap : float, default 0.75
        Fraction of each map's landmarks that are common, in (0, 1];
        ``round(overlap·n)`` landmarks are shared (at least 3).
    snr_db : float, default 40
        Signal-to-noise ratio in dB (finite).
    rng : None, int, SeedSequence or Generator
        Randomness, normalised with ``np.random.default_rng``.
    aspect : float, default 1
        Width / height of each map's rectangle, > 0.
    unrelated : bool, default False
        Draw map q's landmarks of the overlap strip independently of map p's,
        so the maps share no landmark (for false-merge rates); everything
        else, σ included, is as in the related scenario.

    Returns
    -------
    Scenario

    Raises
    ------
    ValueError
        On out-of-range arguments.
    """
    n, c = _check_scenario(n_landmarks, overlap, snr_db, aspect)
    rng = np.random.default_rng(rng)
    # Unit density: each map's rectangle has area n; the strip has area c.
    height = np.sqrt(n / aspect)
    width = aspect * height
    strip = width * c / n
    shift = width - strip
    common = _uniform(rng, c, shift, width, height)
    own_p = _uniform(rng, n - c, 0.0, shift, height)
    own_q = _uniform(rng, n - c, width, width + shift, height)
    truth = np.concatenate([common, own_p, own_q])
    ids_p = np.concatenate([np.arange(c), c + np.arange(n - c)])
    ids_q = np.concatenate([np.arange(c), n + np.arange(n - c)])
    world = truth
    if unrelated:
        # q's strip gets its own landmarks; σ is still set from the related world.
        truth = np.concatenate([truth, _uniform(rng, c, shift, width, height)])
        ids_q[:c] = 2 * n - c + np.arange(c)
    ids_p = ids_p[rng.permutation(n)]
    ids_q = ids_q[rng.permutation(n)]

    sigma, sigma_bar2 = sigma_from_snr(world, snr_db)
    theta = float(rng.uniform(-np.pi, np.pi))
    t = rng.uniform(-width, width, size=2)
    p = truth[ids_p] + rng.normal(0.0, sigma, size=(n, 2))
    q = rotate(np.float64(theta), truth[ids_q]) + t + rng.normal(0.0, sigma, size=(n, 2))
    return Scenario(p, q, ids_p, ids_q, truth, sigma, theta, t, float(snr_db), sigma_bar2)


def _uniform(rng: np.random.Generator, k: int, x0: float, x1: float, height: float) -> np.ndarray:
    return np.column_stack([rng.uniform(x0, x1, k), rng.uniform(0.0, height, k)])


def _check_scenario(n_landmarks, overlap, snr_db, aspect) -> tuple[int, int]:
    if isinstance(n_landmarks, bool) or int(n_landmarks) != n_landmarks or n_landmarks < 3:
        raise ValueError(f"n_landmarks must be an integer >= 3, got {n_landmarks!r}")
    if not (np.isfinite(overlap) and 0.0 < overlap <= 1.0):
        raise ValueError(f"overlap must be in (0, 1], got {overlap!r}")
    if not np.isfinite(snr_db):
        raise ValueError(f"snr_db must be a finite number, got {snr_db!r}")
    if not (np.isfinite(aspect) and aspect > 0):
        raise ValueError(f"aspect must be a positive number, got {aspect!r}")
    n = int(n_landmarks)
    c = int(np.floor(overlap * n + 0.5))
    if c < 3:
        raise ValueError(
            f"overlap * n_landmarks must round to at least 3 common landmarks, got {overlap}*{n}"
        )
    return n, c
