"""Synthetic pairs of overlapping landmark maps with ground truth.

Two robots explore neighbouring rectangles of a world with landmarks at unit
density (counting the landmarks either map holds). Map q's rectangle is map
p's shifted right, so that the two share an overlap window holding
``c = round(overlap·n)`` common landmarks of each map's ``n``. Two layouts:

- ``strip`` (the paper's): the overlap holds only the c common landmarks;
  each map's ``n - c`` unshared ones lie in its own part.
- ``interleaved``: each agent detects a landmark of the overlap with
  probability ``p_detect``, so unshared landmarks lie among the common ones.
  Each map holds ``u = round(c (1 - p_detect) / p_detect)`` unshared
  landmarks in the overlap (the expected count given c detected by both)
  and the rest in its own part; fixing the counts keeps every trial's map
  size and overlap as stated.

``clutter`` adds ``round(clutter·n)`` spurious landmarks per map, uniform
over its window (a Poisson process given its count), seen by one map only.
Map q's frame is the world seen through a uniform random rotation and a
random translation, ``q = R(θ) x + t``; both maps then get independent
zero-mean Gaussian noise with σ set from the SNR:

    SNR_dB = 10 log10(σ̄² / (2σ²)),

σ̄² the sample variance of the edge lengths of the Delaunay graph of the true
landmarks (clutter excluded). With ``anisotropy = 0`` the noise is N(0, σ²)
per coordinate; otherwise it is range-bearing-like: each agent drives along
its window's midline, and a landmark's cross-range standard deviation grows
with its distance from that path (see ``_relative_sd``), scaled so that σ²
stays the map's mean per-coordinate variance. Each map's per-landmark
covariances are returned in its own frame. Row order of each map is
shuffled so indices carry no truth.

``make_pairs`` draws many trials, each from its own seed; ``make_pair`` is
its single case, so the order of the random draws lives in one place: per
trial, the uniforms of the landmark blocks (x then y of each block in world
row order: common, then p's unshared, q's unshared[, q's unrelated common
ones], p's clutter, q's clutter), two permutations, θ, t, and the two maps'
normal noise.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields

import numpy as np

from scipy.spatial import Delaunay

from ._validation import check_points, check_rng
from .alignment import covariance_in_p_frame, rotate

#: Width / height of each map's rectangle (strip layout).
DEFAULT_ASPECT = 1.0
#: Where unshared landmarks lie (see the module docstring).
LAYOUTS = ("strip", "interleaved")
#: Interleaved layout: probability that an agent detects a landmark of the overlap.
DEFAULT_P_DETECT = 0.9
#: Largest |SNR| in dB: σ then lies within 10^±15 of the landmarks' spread, well inside what
#: ``merge_maps`` accepts (far beyond any SNR at which matching changes).
MAX_SNR_DB = 300.0
#: Largest map drawn, true plus spurious landmarks (``n_landmarks · (1 + clutter)``): the methods
#: take 0.3-1 GB at 10⁵ landmarks per map, so several GB here.
MAX_MAP_LANDMARKS = 10**6
#: Map rectangles' width / height, from 1 / ``MAX_ASPECT`` to ``MAX_ASPECT`` (beyond, a map is a line).
MAX_ASPECT = 1000.0
#: Largest ``anisotropy`` (cross-range noise up to 1 + this times the range noise).
MAX_ANISOTROPY = 1000.0


@dataclass(frozen=True)
class Scenario:
    """One synthetic map pair and its ground truth.

    Attributes
    ----------
    p, q : (m, 2) ndarray
        Noisy landmark maps, each in its own frame (m = n + clutter rows).
    ids_p, ids_q : (m,) int ndarray
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
    cov_p, cov_q : (m, 2, 2) ndarray
        Each row's noise covariance in its map's frame.
    density : float
        Landmarks per unit area of each map.
    p_shared : float
        Fraction of q's rows inside the overlap that are common: with
        ``density`` the prior of an association that knows the layout.
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
    cov_p: np.ndarray
    cov_q: np.ndarray
    density: float
    p_shared: float

    @functools.cached_property
    def n_common(self) -> int:
        return int(np.intersect1d(self.ids_p, self.ids_q).size)


def bend(points, angle: float, fraction: float = 0.4, direction=None) -> np.ndarray:
    """A map bent as heading drift bends it: its far part turned rigidly about a hinge.

    The landmarks beyond the ``1 - fraction`` quantile along ``direction``
    (through the map's centroid) turn by ``angle`` about the point of that
    line at the quantile; the others stay. The scenarios of ``make_pairs``
    are rigid; this makes the bent maps ``merging.residual_match`` is for.

    Parameters
    ----------
    points : (n, 2) array_like
        The map.
    angle : float
        Rotation of the far part, radians (counter-clockwise).
    fraction : float, default 0.4
        Share of the landmarks turned, in (0, 1).
    direction : (2,) array_like, optional
        Where the turned part lies from the centroid; default the map's
        principal axis (either way along it).

    Returns
    -------
    (n, 2) ndarray
        The bent map (a copy; rows in the same order).

    Raises
    ------
    ValueError
        On an invalid map, ``fraction`` outside (0, 1) or a ``direction``
        that is not a finite non-zero 2-vector.
    """
    points = check_points(points, "points")
    if not 0 < fraction < 1:
        raise ValueError(f"fraction must be in (0, 1), got {fraction!r}")
    centre = points.mean(axis=0)
    if direction is None:
        axis = np.linalg.svd(points - centre, full_matrices=False)[2][0]
    else:
        axis = np.asarray(direction, dtype=float)
        if axis.shape != (2,) or not np.all(np.isfinite(axis)) or not np.any(axis):
            raise ValueError(f"direction must be a finite non-zero (2,) vector, got {direction!r}")
        axis = axis / np.linalg.norm(axis)
    along = (points - centre) @ axis
    cut = np.quantile(along, 1 - fraction)
    hinge = centre + cut * axis
    out = points.copy()
    far = along > cut
    out[far] = hinge + rotate(float(angle), points[far] - hinge)
    return out


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
    (``snr_db``, ``density`` and ``p_shared`` are shared) plus ``n_common``;
    ``batch[k]`` is trial k's ``Scenario``.
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
    cov_p: np.ndarray
    cov_q: np.ndarray
    density: float
    p_shared: float

    def __len__(self) -> int:
        return len(self.p)

    def take(self, trials: np.ndarray) -> "ScenarioBatch":
        """The trials ``trials`` as a batch of their own."""
        return ScenarioBatch(*(getattr(self, f.name) if f.name in _SHARED else getattr(self, f.name)[trials]
                               for f in fields(self)))

    def __getitem__(self, k: int) -> Scenario:
        return Scenario(self.p[k], self.q[k], self.ids_p[k], self.ids_q[k], self.truth[k], float(self.sigma[k]),
                        float(self.theta[k]), self.t[k], self.snr_db, float(self.sigma_bar2[k]), self.cov_p[k],
                        self.cov_q[k], self.density, self.p_shared)


_SHARED = ("snr_db", "density", "p_shared")


@dataclass(frozen=True)
class SpawnedSeeds:
    """The trial seeds ``SeedSequence(entropy, spawn_key=(*spawn_prefix, k))``, k in ``ks``, as one sequence.

    A compact, checked sequence of those ``SeedSequence`` objects
    (``seeds[i]``): ``make_pairs`` seeds its trials from it exactly as from
    the list of them, with numpy's own ``default_rng``.

    Parameters
    ----------
    entropy : int
        The root seed, >= 0.
    spawn_prefix : tuple of int
        Spawn-key words before the trial index (e.g. a cell key), each >= 0.
    ks : (B,) array_like of int
        Trial indices, 0 <= k < 2**63.

    Raises
    ------
    ValueError
        If ``entropy``, a prefix word or a trial index is negative or not an integer.
    """

    entropy: int
    spawn_prefix: tuple
    ks: np.ndarray

    def __post_init__(self):
        ks = np.asarray(self.ks)
        if not all(isinstance(v, (int, np.integer)) and v >= 0 for v in (self.entropy, *self.spawn_prefix)):
            raise ValueError("entropy and spawn_prefix must be non-negative ints")
        if ks.ndim != 1 or (ks.size and (ks.dtype.kind not in "iu" or ks.min() < 0 or ks.max() >= 2**63)):
            raise ValueError(f"ks must be a 1-D array of non-negative ints below 2**63, got {self.ks!r}")
        object.__setattr__(self, "spawn_prefix", tuple(int(v) for v in self.spawn_prefix))
        object.__setattr__(self, "ks", ks.astype(np.int64))

    def __len__(self) -> int:
        return len(self.ks)

    def __getitem__(self, i: int) -> np.random.SeedSequence:
        return np.random.SeedSequence(self.entropy, spawn_key=(*self.spawn_prefix, int(self.ks[i])))

    def generators(self):
        """Yield, per trial, ``np.random.default_rng`` of its seed."""
        for i in range(len(self)):
            yield np.random.default_rng(self[i])


def make_pair(
    n_landmarks: int = 100,
    overlap: float = 0.75,
    snr_db: float = 40.0,
    *,
    rng=None,
    aspect: float = DEFAULT_ASPECT,
    unrelated: bool = False,
    layout: str = "strip",
    p_detect: float = DEFAULT_P_DETECT,
    clutter: float = 0.0,
    anisotropy: float = 0.0,
) -> Scenario:
    """Draw one overlapping map pair: ``make_pairs`` with a single seed.

    Parameters
    ----------
    n_landmarks : int, default 100
        True landmarks per map, >= 3.
    overlap : float, default 0.75
        Fraction of each map's landmarks that are common, in (0, 1];
        ``round(overlap·n)`` landmarks are shared (at least 3).
    snr_db : float, default 40
        Signal-to-noise ratio in dB (finite).
    rng : None, int, SeedSequence or Generator
        Randomness, normalised with ``np.random.default_rng``.
    aspect : float, default 1
        Width / height of each map's rectangle in the strip layout, > 0.
    unrelated : bool, default False
        Draw map q's common landmarks independently of map p's, so the maps
        share no landmark (for false-merge rates); everything else, σ
        included, is as in the related scenario.
    layout : {"strip", "interleaved"}, default "strip"
        Where unshared landmarks lie: only outside the overlap (the paper's
        setting) or also among the common ones (see the module docstring).
    p_detect : float, default 0.9
        Interleaved layout: probability that an agent detects a landmark of
        the overlap, in (0, 1].
    clutter : float, default 0
        Spurious landmarks per map as a fraction of ``n_landmarks``, >= 0.
    anisotropy : float, default 0
        Growth of the cross-range standard deviation with distance from the
        agent's path, >= 0; 0 is isotropic noise.

    Returns
    -------
    Scenario

    Raises
    ------
    ValueError
        On out-of-range arguments.
    """
    return make_pairs(n_landmarks, overlap, snr_db, [check_rng(rng)], aspect=aspect, unrelated=unrelated,
                      layout=layout, p_detect=p_detect, clutter=clutter, anisotropy=anisotropy)[0]


def make_pairs(n_landmarks: int, overlap: float, snr_db: float, seeds, *, aspect: float = DEFAULT_ASPECT,
               unrelated: bool = False, layout: str = "strip", p_detect: float = DEFAULT_P_DETECT,
               clutter: float = 0.0, anisotropy: float = 0.0) -> ScenarioBatch:
    """Draw one map pair per seed (see ``make_pair`` for the arguments).

    Parameters
    ----------
    seeds : sequence of None, int, SeedSequence or Generator, or SpawnedSeeds
        One per trial; each is normalised with ``np.random.default_rng`` and
        is the only randomness of its trial, so a trial is the same alone or
        in any batch. ``SpawnedSeeds`` is a sequence of SeedSequences.

    Returns
    -------
    ScenarioBatch
    """
    n, c = check_scenario(n_landmarks, overlap, snr_db, aspect, layout, p_detect, clutter, anisotropy)
    if len(seeds) == 0:
        raise ValueError("seeds must hold at least one seed (one per trial)")
    g = _geometry(n, c, aspect, layout, p_detect, clutter)
    B, m = len(seeds), n + g.k
    blocks = g.blocks + ([g.blocks[0]] if unrelated else []) + g.clutter
    u, perm_p, perm_q, u3, z = _pair_draws(seeds, 2 * sum(count for count, _, _ in blocks), m)
    world = _world(blocks, g.height, u)
    # σ comes from the related world (the true landmarks of either map), also for unrelated pairs.
    sigma, sigma_bar2 = sigmas_from_snr(world[:, : 2 * n - c], float(snr_db))
    base_p, base_q = _world_rows(n, c, g.k, unrelated)
    ids_p, ids_q = base_p[perm_p], base_q[perm_q]
    theta = -np.pi + (np.pi - -np.pi) * u3[:, 0]
    t = -g.width + (g.width - -g.width) * u3[:, 1:]
    p, q, cov_p, cov_q = _noisy_maps(world, ids_p, ids_q, sigma, (theta, t), z, g.height, anisotropy)
    return ScenarioBatch(p, q, ids_p, ids_q, world, sigma, theta, t, float(snr_db), sigma_bar2,
                         np.full(B, 0 if unrelated else c), cov_p, cov_q, g.density, g.p_shared)


def _pair_draws(seeds, n_uniform: int, m: int):
    """Each trial's random numbers, from its own seed: the uniforms of its world, the orders of its two
    maps' rows, the uniforms of its rigid motion and the standard normals of its noise."""
    B = len(seeds)
    u = np.empty((B, n_uniform))
    perm_p, perm_q = np.empty((B, m), np.intp), np.empty((B, m), np.intp)
    u3, z = np.empty((B, 3)), np.empty((B, 2, m, 2))
    for k, seed in enumerate(seeds):
        rng = np.random.default_rng(check_rng(seed, "each seed"))
        # One call per run of draws: ``uniform(a, b)`` is ``a + (b - a)·random``
        # and ``normal(0, σ)`` is ``σ·standard_normal``, so scaling afterwards
        # gives the same bits as drawing block by block.
        rng.random(out=u[k])
        perm_p[k] = rng.permutation(m)
        perm_q[k] = rng.permutation(m)
        rng.random(out=u3[k])
        rng.standard_normal(out=z[k].reshape(-1))
    return u, perm_p, perm_q, u3, z


def _world_rows(n: int, c: int, k: int, unrelated: bool):
    """The world rows of map p's and map q's landmarks before each map's own order (``k`` clutter each)."""
    # Ids are world rows: p's landmarks are 0..n-1, q's own n..2n-c-1; q's
    # common ones are p's (fresh rows when unrelated), then each map's clutter.
    fresh = 2 * n - c + (c if unrelated else 0)
    base_p = np.concatenate([np.arange(n), fresh + np.arange(k)])
    base_q = np.concatenate([(2 * n - c if unrelated else 0) + np.arange(c), n + np.arange(n - c),
                             fresh + k + np.arange(k)])
    return base_p, base_q


def _noisy_maps(world, ids_p, ids_q, sigma, motion: tuple, z, height: float, anisotropy: float):
    """Maps p (world frame) and q (moved by ``motion``, the trials' θ and t) with their noise, and its covariances."""
    theta, t = motion
    B, m = ids_p.shape
    rows = np.arange(B)[:, None]
    if anisotropy == 0:
        noise = sigma[:, None, None, None] * z
        p = world[rows, ids_p] + noise[:, 0]
        q = rotate(theta, world[rows, ids_q]) + t[:, None, :] + noise[:, 1]
        cov_p = cov_q = sigma[:, None, None, None] ** 2 * np.eye(2)
        cov_p, cov_q = (np.broadcast_to(cov_p, (B, m, 2, 2)),) * 2
    else:
        sd_p = sigma[:, None, None] * _relative_sd(world[rows, ids_p, 1], height, anisotropy)
        sd_q = sigma[:, None, None] * _relative_sd(world[rows, ids_q, 1], height, anisotropy)
        p = world[rows, ids_p] + sd_p * z[:, 0]
        # q's noise is drawn in the world frame, where its axes are along and across the path.
        q = rotate(theta, world[rows, ids_q] + sd_q * z[:, 1]) + t[:, None, :]
        cov_p = sd_p[..., None] ** 2 * np.eye(2)
        cov_q = covariance_in_p_frame(-theta, sd_q[..., None] ** 2 * np.eye(2))
    return p, q, cov_p, cov_q


@dataclass(frozen=True)
class _Geometry:
    """Where a scenario's landmarks lie: blocks ``(count, x0, x1)`` of uniform
    landmarks (y in [0, height]) in world-row order, and the association prior."""

    blocks: list
    clutter: list
    k: int
    height: float
    width: float
    density: float
    p_shared: float


def _geometry(n: int, c: int, aspect: float, layout: str, p_detect: float, clutter: float) -> _Geometry:
    # An overlap landmark is kept by one agent only with probability
    # d(1 - d) and by both with d²: u of each map's landmarks in the overlap
    # are unshared, fixed at their expected count (capped by what the map has)
    # so that every trial has the stated map size and overlap.
    u = min(int(np.floor(c * (1 - p_detect) / p_detect + 0.5)), n - c) if layout == "interleaved" else 0
    height = np.sqrt(n / aspect)
    # Unit density of the landmarks either map holds: p's window has area
    # n + u, of which the overlap c + 2u. (With u = 0 this is the strip layout,
    # computed exactly as it always was.)
    width = aspect * height * ((n + u) / n)
    shift = width - width * (c + 2 * u) / (n + u)
    own = n - c - u
    overlap = (shift, width)
    blocks = [(c, *overlap), (u, *overlap), (own, 0.0, shift), (u, *overlap), (own, width, width + shift)]
    k = int(np.floor(clutter * n + 0.5))
    return _Geometry(blocks, [(k, 0.0, width), (k, shift, width + shift)], k, height, width,
                     density=(n + k) / (n + u),
                     # Of q's rows in the overlap, the common ones.
                     p_shared=c / (c + u + k * (c + 2 * u) / (n + u)))


def _relative_sd(y: np.ndarray, height: float, anisotropy: float) -> np.ndarray:
    """Per-landmark noise standard deviations along x and y, in units of σ.

    An agent drives along its window's midline y = height / 2 and sees a
    landmark at distance d across it: range noise (across the path, y) stays
    1, cross-range noise (along the path, x) is ``1 + anisotropy·d/(height/2)``
    like a bearing error. Scaled so that the map's mean per-coordinate
    variance is 1, i.e. σ keeps its meaning.
    """
    cross = 1.0 + anisotropy * np.abs(y - height / 2) / (height / 2)
    scale = np.sqrt(np.mean((cross**2 + 1.0) / 2, axis=-1, keepdims=True))
    return np.stack([cross, np.ones_like(cross)], axis=-1) / scale[..., None]


def _world(blocks, height: float, u: np.ndarray) -> np.ndarray:
    """True landmarks (B, L, 2) from the uniforms; row = landmark id."""
    lo, span, col_x, col_y, at = [], [], [], [], 0
    for k, x0, x1 in blocks:  # k uniforms for x in [x0, x1], then k for y in [0, height]
        lo += [x0] * k + [0.0] * k
        span += [x1 - x0] * k + [height - 0.0] * k
        col_x += range(at, at + k)
        col_y += range(at + k, at + 2 * k)
        at += 2 * k
    values = np.asarray(lo) + np.asarray(span) * u
    return np.stack([values[:, col_x], values[:, col_y]], axis=2)


class ScenarioError(ValueError):
    """A scenario argument out of its range: ``argument`` names it, ``value`` is what was given and
    ``rule`` says what is allowed (so that a config validator can name its own key)."""

    def __init__(self, argument: str, value, rule: str):
        super().__init__(f"{argument} {rule}, got {value!r}")
        self.argument, self.value, self.rule = argument, value, rule


def _real(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and bool(
        np.isfinite(value))


def check_scenario(n_landmarks, overlap, snr_db, aspect, layout="strip", p_detect=DEFAULT_P_DETECT, clutter=0.0,
                   anisotropy=0.0) -> tuple[int, int]:
    """Validate scenario arguments; return ``(n, c)``: true and common landmarks per map.

    Raises
    ------
    ScenarioError
        Naming the first argument out of its range.
    """
    if not (_real(n_landmarks) and int(n_landmarks) == n_landmarks and n_landmarks >= 3):
        raise ScenarioError("n_landmarks", n_landmarks, "must be an integer >= 3")
    if not (_real(overlap) and 0.0 < overlap <= 1.0):
        raise ScenarioError("overlap", overlap, "must be in (0, 1]")
    if not (_real(snr_db) and abs(snr_db) <= MAX_SNR_DB):
        raise ScenarioError("snr_db", snr_db, f"must be a number of dB in [-{MAX_SNR_DB:g}, {MAX_SNR_DB:g}]")
    if not (_real(aspect) and 1 / MAX_ASPECT <= aspect <= MAX_ASPECT):
        raise ScenarioError("aspect", aspect, f"must be in [{1 / MAX_ASPECT:g}, {MAX_ASPECT:g}]")
    if layout not in LAYOUTS:
        raise ScenarioError("layout", layout, f"must be one of {list(LAYOUTS)}")
    if not (_real(p_detect) and 0.0 < p_detect <= 1.0):
        raise ScenarioError("p_detect", p_detect, "must be a probability in (0, 1]")
    if not (_real(clutter) and clutter >= 0):
        raise ScenarioError("clutter", clutter, "must be >= 0 (spurious landmarks per true landmark)")
    if not (_real(anisotropy) and 0 <= anisotropy <= MAX_ANISOTROPY):
        raise ScenarioError("anisotropy", anisotropy, f"must be in [0, {MAX_ANISOTROPY:g}] (0 is isotropic noise)")
    n = int(n_landmarks)
    if n * (1 + clutter) > MAX_MAP_LANDMARKS:
        raise ScenarioError("n_landmarks", n_landmarks, f"must keep n_landmarks * (1 + clutter) at most "
                                                        f"{MAX_MAP_LANDMARKS:,} landmarks per map (clutter {clutter})")
    c = int(np.floor(overlap * n + 0.5))
    if c < 3:
        raise ScenarioError("overlap", overlap, f"must make overlap * n_landmarks round to at least 3 common "
                                                f"landmarks (n_landmarks {n})")
    return n, c


#: How agents' discs are arranged in ``make_group``; neighbouring agents' discs share
#: the fraction ``overlap`` of their area:
#:
#: - ``chain``: agents on a line, agent i next to i ± 1;
#: - ``ring``: agents on a circle, the last next to the first (the loop closes);
#: - ``star``: agent 0 in the centre, every other agent next to it (and to
#:   neighbours of its own when many crowd around the centre);
#: - ``random``: agent i next to an earlier agent drawn uniformly, in a
#:   uniform direction (a random tree, with chance overlaps besides).
TOPOLOGIES = ("chain", "ring", "star", "random")
#: Most agents in one synthetic team (strangers included).
MAX_AGENTS = 1000


@dataclass(frozen=True)
class Team:
    """A synthetic team of agents' maps and its ground truth (``make_group``).

    Attributes
    ----------
    maps : list of (n_i, 2) ndarray
        Each agent's noisy landmark map in its own frame (rows shuffled).
    ids : list of (n_i,) int ndarray
        True landmark id of each row; equal ids are the same landmark.
    truth : (L, 2) ndarray
        True position of landmark id k in the world frame.
    theta : (N,) ndarray
        Agent i's frame: ``maps[i] ≈ R(θ_i) truth[ids[i]] + t_i`` (NaN for strangers,
        whose landmarks belong to no world of the team's).
    t : (N, 2) ndarray
    sigma : float
        Per-coordinate noise standard deviation of every map.
    covs : list of (n_i, 2, 2) ndarray
        Each row's noise covariance in its map's frame (σ² I).
    stranger : (N,) bool ndarray
        Agents that share no landmark with anyone (they must stay unplaced).
    centres : (N, 2) ndarray
        Centre of each agent's window in the world frame (a stranger's in its own world).
    snr_db : float
    topology : str
    """

    maps: list
    ids: list
    truth: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    sigma: float
    covs: list
    stranger: np.ndarray
    centres: np.ndarray
    snr_db: float
    topology: str

    @property
    def n_agents(self) -> int:
        return len(self.maps)


def _lens_fraction(d, r: float):
    """Area shared by two discs of radius r at centre distance d, as a fraction of one disc."""
    d = np.clip(np.asarray(d, dtype=float) / (2 * r), 0.0, 1.0)
    return (2 / np.pi) * (np.arccos(d) - d * np.sqrt(1 - d**2))


def _neighbour_distance(overlap: float, r: float) -> float:
    """Centre distance at which two discs of radius r share ``overlap`` of their area (bisection)."""
    lo, hi = 0.0, 2 * r
    for _ in range(60):  # 2r / 2^60: far below any landmark spacing
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _lens_fraction(mid, r) > overlap else (lo, mid)
    return 0.5 * (lo + hi)


def _window_centres(n_agents: int, topology: str, d: float, rng: np.random.Generator) -> np.ndarray:
    """Window centres: neighbours in the topology's graph lie d apart (see ``make_group``)."""
    k = np.arange(n_agents)
    if topology == "chain":
        return np.stack([k * d, np.zeros(n_agents)], axis=1)
    if topology == "ring":
        # Consecutive centres, the last and the first included, are one chord d apart.
        radius = d / (2 * np.sin(np.pi / n_agents))
        phi = 2 * np.pi * k / n_agents
        return radius * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    if topology == "star":
        phi = 2 * np.pi * (k[1:] - 1) / max(n_agents - 1, 1)
        return np.concatenate([np.zeros((1, 2)), d * np.stack([np.cos(phi), np.sin(phi)], axis=1)])
    # random: each agent next to one earlier agent drawn uniformly, in a uniform direction.
    u = rng.random((n_agents, 2))
    centres = np.zeros((n_agents, 2))
    for i in range(1, n_agents):
        parent = int(u[i, 0] * i)
        phi = 2 * np.pi * u[i, 1]
        centres[i] = centres[parent] + d * np.array([np.cos(phi), np.sin(phi)])
    return centres


def _window_landmarks(centres: np.ndarray, r: float, density: float, rng: np.random.Generator) -> np.ndarray:
    """Landmarks uniform at ``density`` over the union of discs of radius r (a Poisson process)."""
    lo, hi = centres.min(axis=0) - r, centres.max(axis=0) + r
    count = rng.poisson(density * np.prod(hi - lo))
    x = lo + (hi - lo) * rng.random((count, 2))
    seen = np.zeros(count, dtype=bool)
    for c in centres:
        seen |= np.sum((x - c) ** 2, axis=1) <= r * r
    return x[seen]


def make_group(n_agents: int = 5, n_landmarks: int = 100, overlap: float = 0.5, snr_db: float = 20.0, *,
               layout: str = "strip", topology: str = "ring", n_strangers: int = 0,
               p_detect: float = DEFAULT_P_DETECT, rng=None) -> Team:
    """Draw a synthetic team: ``n_agents`` robots whose maps overlap along a topology.

    Each agent explores a disc of area ``n_landmarks`` in a world of landmarks uniform at unit density (a Poisson
    process over the union of the discs), so a map holds ``n_landmarks`` landmarks on average. Neighbouring agents'
    discs share the fraction ``overlap`` of their area, along ``topology`` (``TOPOLOGIES`` describes each). Agents
    further apart share what their discs' geometry gives (nothing beyond 2 radii). ``layout="strip"``: an agent sees
    every landmark of its disc; ``"interleaved"``: each landmark independently with probability ``p_detect`` (the
    density is 1 / ``p_detect``, keeping the mean map size), so landmarks only one agent holds lie among the shared
    ones. Each agent's frame is the world through a uniform random rotation and a translation uniform over the
    world's extent, then N(0, σ²) noise per coordinate, σ from ``snr_db`` as in ``make_pair`` with σ̄² the mean over
    agents of the edge-length variance of the Delaunay graph of the agent's own true landmarks. ``n_strangers`` more
    agents map discs of worlds of their own (same size, density and σ): they share nothing with the team.

    The random draws, in order: the random topology's placements, the world's
    landmarks, the detections, then per agent (strangers last) its own
    world's landmarks (strangers only), frame, noise and row permutation.

    Parameters
    ----------
    n_agents : int, default 5
        Agents of the team, >= 2.
    n_landmarks : int, default 100
        Mean landmarks per map, >= 3.
    overlap : float, default 0.5
        Share of a disc's area common to neighbouring agents, in (0, 1).
    snr_db : float, default 20
    layout : {"strip", "interleaved"}, default "strip"
    topology : {"chain", "ring", "star", "random"}, default "ring"
    n_strangers : int, default 0
        Agents unrelated to the team, appended after it, >= 0.
    p_detect : float, default 0.9
        Interleaved layout: probability that an agent sees a landmark of its disc, in (0, 1].
    rng : None, int, SeedSequence or Generator

    Returns
    -------
    Team

    Raises
    ------
    ScenarioError
        On an argument out of its range (naming it).
    """
    _check_group(n_agents, n_landmarks, overlap, snr_db, layout, topology, n_strangers, p_detect)
    rng = np.random.default_rng(check_rng(rng))
    disc = (np.sqrt(n_landmarks / np.pi), 1.0 if layout == "strip" else float(p_detect))  # radius, detection
    world, centres, seen = _team_world(int(n_agents), topology, overlap, disc, rng)
    sigma = _team_sigma(world, seen, snr_db)
    maps, ids, truth, centre, theta, t = _agent_maps(world, centres, seen, int(n_strangers), disc, sigma, rng)
    stranger = np.arange(len(maps)) >= int(n_agents)
    theta[stranger], t[stranger] = np.nan, np.nan
    return Team(maps=maps, ids=ids, truth=truth, theta=theta, t=t, sigma=sigma,
                covs=[np.broadcast_to(sigma**2 * np.eye(2), (len(m), 2, 2)) for m in maps], stranger=stranger,
                centres=centre, snr_db=float(snr_db), topology=topology)


def _check_group(n_agents, n_landmarks, overlap, snr_db, layout, topology, n_strangers, p_detect) -> None:
    """A ScenarioError naming the first of ``make_group``'s arguments out of its range."""
    check_scenario(n_landmarks, 1.0, snr_db, DEFAULT_ASPECT, layout, p_detect)
    if not (_real(n_agents) and int(n_agents) == n_agents and 2 <= n_agents <= MAX_AGENTS):
        raise ScenarioError("n_agents", n_agents, f"must be an integer in [2, {MAX_AGENTS}]")
    if not (_real(n_strangers) and int(n_strangers) == n_strangers and 0 <= n_strangers <= MAX_AGENTS - n_agents):
        raise ScenarioError("n_strangers", n_strangers, f"must be an integer in [0, {MAX_AGENTS} - n_agents]")
    if not (_real(overlap) and 0.0 < overlap < 1.0):
        raise ScenarioError("overlap", overlap, "must be in (0, 1) (the share of neighbouring discs' area)")
    if topology not in TOPOLOGIES:
        raise ScenarioError("topology", topology, f"must be one of {list(TOPOLOGIES)}")
    if n_landmarks * (n_agents + n_strangers) > MAX_MAP_LANDMARKS:
        raise ScenarioError("n_landmarks", n_landmarks, f"must keep n_landmarks * (n_agents + n_strangers) at "
                                                        f"most {MAX_MAP_LANDMARKS:,}")


def _team_world(n_agents: int, topology: str, overlap: float, disc: tuple, rng: np.random.Generator):
    """The team's discs' centres, the world's landmarks over them and which of them each agent sees.

    ``disc`` is (radius, detection probability).
    """
    r, detect = disc
    centres = _window_centres(n_agents, topology, _neighbour_distance(overlap, r), rng)
    world = _window_landmarks(centres, r, 1.0 / detect, rng)
    seen = [(np.sum((world - c) ** 2, axis=1) <= r * r) & (rng.random(len(world)) < detect) for c in centres]
    return world, centres, seen


def _team_sigma(world: np.ndarray, seen: list, snr_db: float) -> float:
    """The team's σ at ``snr_db``, σ̄² the mean over agents of their own true landmarks' (``seen``) σ̄²."""
    # σ̄² of each agent's own disc, averaged: the union of the discs is not convex, and its Delaunay
    # graph would bridge the gaps between them with long edges (a chain's σ̄² twice a ring's).
    sigma_bar2 = np.mean([sigma_from_snr(world[s], 0.0)[1] for s in seen])
    return float(np.sqrt(sigma_bar2 / (2.0 * 10.0 ** (float(snr_db) / 10.0))))


def _agent_maps(world, centres, seen, n_strangers: int, disc: tuple, sigma: float, rng: np.random.Generator):
    """Each agent's map (the team's, then ``n_strangers`` strangers' with worlds of their own), in its own frame.

    Returns the maps, their landmarks' rows of the joint truth, the joint truth, the discs' centres
    and the agents' frames (θ, t). ``disc`` is (radius, detection probability).
    """
    r, detect = disc
    truth, ids, centre = [world], [np.flatnonzero(s) for s in seen], list(centres)
    n_agents = len(centres)
    extent = float(np.max(np.ptp(world, axis=0)))
    maps, theta, t = [], [], []
    for i in range(n_agents + n_strangers):
        if i >= n_agents:
            own = _window_landmarks(np.zeros((1, 2)), r, 1.0 / detect, rng)
            own = own[rng.random(len(own)) < detect]
            ids.append(sum(len(w) for w in truth) + np.arange(len(own)))
            truth.append(own)
            centre.append(np.zeros(2))
        u = rng.random(3)
        theta.append(-np.pi + 2 * np.pi * u[0])
        t.append(extent * (2 * u[1:] - 1))
        x = np.concatenate(truth)[ids[i]]
        maps.append(rotate(theta[i], x) + t[i] + sigma * rng.standard_normal(x.shape))
        perm = rng.permutation(len(x))
        maps[i], ids[i] = maps[i][perm], ids[i][perm]
    return maps, ids, np.concatenate(truth), np.array(centre), np.array(theta), np.array(t)
