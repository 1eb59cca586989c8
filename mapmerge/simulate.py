"""Synthetic pairs of overlapping landmark maps with ground truth.

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

``make_pairs`` draws many trials, each from its own seed; ``make_pair`` is
its single case, so the order of the random draws lives in one place: per
trial, the uniforms of the landmark blocks (x then y of the common strip,
p's own part, q's own part[, q's unrelated strip]), two permutations, θ,
t, and the two maps' normal noise.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields

import numpy as np

from scipy.spatial import Delaunay

from .alignment import rotate

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


@dataclass(frozen=True)
class ScenarioBatch:
    """B synthetic map pairs of one scenario, stacked along a leading axis.

    The attributes are those of ``Scenario`` with a batch axis in front
    (``snr_db`` is shared); ``batch[k]`` is trial k's ``Scenario``.
    """

    p: np.ndarray
    q: np.ndarray
    ids_p: np.ndarray
    ids_q: np.ndarray
    truth: np.ndarray
    sigma: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    snr_db: float
    sigma_bar2: np.ndarray
    n_common: np.ndarray

    def __len__(self) -> int:
        return len(self.p)

    def take(self, trials: np.ndarray) -> "ScenarioBatch":
        """The trials ``trials`` as a batch of their own."""
        return ScenarioBatch(*(getattr(self, f.name) if f.name == "snr_db" else getattr(self, f.name)[trials]
                               for f in fields(self)))

    def __getitem__(self, k: int) -> Scenario:
        return Scenario(self.p[k], self.q[k], self.ids_p[k], self.ids_q[k], self.truth[k], float(self.sigma[k]),
                        float(self.theta[k]), self.t[k], self.snr_db, float(self.sigma_bar2[k]))


def make_pair(
    n_landmarks: int = 100,
    overlap: float = 0.75,
    snr_db: float = 40.0,
    rng=None,
    aspect: float = DEFAULT_ASPECT,
    unrelated: bool = False,
) -> Scenario:
    """Draw one overlapping map pair: ``make_pairs`` with a single seed.

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
    return make_pairs(n_landmarks, overlap, snr_db, [rng], aspect, unrelated)[0]


def make_pairs(n_landmarks: int, overlap: float, snr_db: float, seeds, aspect: float = DEFAULT_ASPECT,
               unrelated: bool = False) -> ScenarioBatch:
    """Draw one map pair per seed (see ``make_pair`` for the arguments).

    Parameters
    ----------
    seeds : sequence of None, int, SeedSequence or Generator
        One per trial; each is normalised with ``np.random.default_rng`` and
        is the only randomness of its trial, so a trial is the same alone or
        in any batch.

    Returns
    -------
    ScenarioBatch
    """
    n, c = check_scenario(n_landmarks, overlap, snr_db, aspect)
    B = len(seeds)
    height = np.sqrt(n / aspect)
    width = aspect * height
    u = np.empty((B, 2 * c + 4 * (n - c) + (2 * c if unrelated else 0)))
    perm_p, perm_q = np.empty((B, n), np.intp), np.empty((B, n), np.intp)
    u3, z = np.empty((B, 3)), np.empty((B, 2, n, 2))
    for k, seed in enumerate(seeds):
        rng = np.random.default_rng(seed)
        # One call per run of draws: ``uniform(a, b)`` is ``a + (b - a)·random``
        # and ``normal(0, σ)`` is ``σ·standard_normal``, so scaling afterwards
        # gives the same bits as drawing block by block.
        rng.random(out=u[k])
        perm_p[k] = rng.permutation(n)
        perm_q[k] = rng.permutation(n)
        rng.random(out=u3[k])
        rng.standard_normal(out=z[k].reshape(-1))
    world = _world(n, c, width, height, unrelated, u)
    # σ comes from the related world, also for unrelated pairs.
    sigma, sigma_bar2 = sigmas_from_snr(world[:, : 2 * n - c], float(snr_db))
    # p's ids are 0..n-1 before shuffling; q's common ids are p's (or fresh ones when unrelated).
    base_q = np.concatenate([(2 * n - c if unrelated else 0) + np.arange(c), n + np.arange(n - c)])
    ids_p, ids_q = perm_p, base_q[perm_q]
    rows = np.arange(B)[:, None]
    noise = sigma[:, None, None, None] * z
    theta = -np.pi + (np.pi - -np.pi) * u3[:, 0]
    t = -width + (width - -width) * u3[:, 1:]
    p = world[rows, ids_p] + noise[:, 0]
    q = rotate(theta, world[rows, ids_q]) + t[:, None, :] + noise[:, 1]
    return ScenarioBatch(p, q, ids_p, ids_q, world, sigma, theta, t, float(snr_db), sigma_bar2,
                         np.full(B, 0 if unrelated else c))


def _world(n: int, c: int, width: float, height: float, unrelated: bool, u: np.ndarray) -> np.ndarray:
    """True landmarks (B, L, 2) from the uniforms; row = landmark id."""
    shift = width - width * c / n
    blocks = [(c, shift, width), (n - c, 0.0, shift), (n - c, width, width + shift)]
    if unrelated:
        blocks.append((c, shift, width))
    lo, span, col_x, col_y, at = [], [], [], [], 0
    for k, x0, x1 in blocks:  # k uniforms for x in [x0, x1], then k for y in [0, height]
        lo += [x0] * k + [0.0] * k
        span += [x1 - x0] * k + [height - 0.0] * k
        col_x += range(at, at + k)
        col_y += range(at + k, at + 2 * k)
        at += 2 * k
    values = np.asarray(lo) + np.asarray(span) * u
    return np.stack([values[:, col_x], values[:, col_y]], axis=2)


def check_scenario(n_landmarks, overlap, snr_db, aspect) -> tuple[int, int]:
    """Validate scenario arguments; return ``(n, c)``: landmarks per map and common landmarks."""
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
