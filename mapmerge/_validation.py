"""Input checks shared by the public functions (validation at the boundary only)."""

from __future__ import annotations

import math

import numpy as np

#: Largest coordinate magnitude and σ accepted, and the smallest map extent and σ (in map units). Squared
#: distances, their products and qhull's lifted coordinates stay far from overflow and underflow within
#: them (qhull fails on coordinates near 1e160); rescaling a map's units brings any real map inside.
MAX_MAGNITUDE = 1e50
MIN_MAGNITUDE = 1e-50
#: Points are "all on one line" when none lies farther from it than this times the map's extent or its
#: coordinates' magnitude, whichever is larger (a thousand times what qhull's rounding tolerates).
FLAT_TOLERANCE = 1e-12


def float_array(values, message: str) -> np.ndarray:
    """``values`` as a float ndarray, or ``ValueError(message)`` when they are not real numbers
    (complex values too: casting would silently drop their imaginary parts)."""
    try:
        arr = np.asarray(values)
        if np.iscomplexobj(arr):
            raise ValueError
        return arr.astype(float, copy=False)
    except (TypeError, ValueError):
        raise ValueError(message) from None


def check_finite(arr: np.ndarray, name: str) -> None:
    """Raise a one-line ValueError unless every coordinate of ``arr`` is finite and at most ``MAX_MAGNITUDE``."""
    if arr.size and not np.max(np.abs(arr)) <= MAX_MAGNITUDE:  # NaN fails the comparison too
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or inf; all coordinates must be finite")
        raise ValueError(f"{name} has coordinates of magnitude up to {np.max(np.abs(arr)):.3g}; "
                         f"at most {MAX_MAGNITUDE:g} is allowed (rescale the map's units)")


def check_points(points, name: str, min_points: int = 3, geometry: bool = True) -> np.ndarray:
    """Return ``points`` as a float (n, 2) array or raise a one-line ValueError.

    ``geometry`` adds the checks a triangulation needs: no duplicate points and
    not all points on one line.
    """
    arr = float_array(points, f"{name} must be an (n, 2) array of real numbers")
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (n, 2), got {arr.shape}")
    if arr.shape[0] < min_points:
        raise ValueError(f"{name} needs at least {min_points} points, got {arr.shape[0]}")
    check_finite(arr, name)
    if geometry:
        check_geometry(arr[None], name)
    return arr


def check_geometry(maps: np.ndarray, name: str, indexed: bool = False) -> None:
    """Raise a one-line ValueError when one of B finite (B, n, 2) maps has duplicate points or
    all its points on one line, naming it ``name`` (``name[b]`` when ``indexed``)."""
    # Each point as one complex number (the same bits, no arithmetic): a sort puts equal points side by side.
    z = np.sort(np.ascontiguousarray(maps).view(complex)[..., 0], axis=1)
    duplicate = np.any(z[:, 1:] == z[:, :-1], axis=1)
    # All on one line: every point lies within FLAT_TOLERANCE of the extent, or of the coordinates'
    # magnitude when that is larger, from the line along the longest offset from the first point.
    # Rounding blurs a map far from its origin on the scale of its coordinates, not of its extent:
    # qhull finds three points flat when their height is about 1e-15 of their coordinates.
    d = maps - maps[:, :1]
    far = d[np.arange(len(maps)), np.argmax(d[..., 0] ** 2 + d[..., 1] ** 2, axis=1)][:, None]
    cross = np.abs(d[..., 0] * far[..., 1] - d[..., 1] * far[..., 0])
    extent2 = far[:, 0, 0] ** 2 + far[:, 0, 1] ** 2
    magnitude = np.max(np.abs(maps), axis=(1, 2))
    collinear = np.max(cross, axis=1) <= FLAT_TOLERANCE * np.sqrt(extent2) * np.maximum(np.sqrt(extent2), magnitude)
    small = extent2 < MIN_MAGNITUDE**2
    for bad, message in ((duplicate, "contains duplicate points; landmarks must be distinct"),
                         (small, f"points span less than {MIN_MAGNITUDE:g}; rescale the map's units"),
                         (collinear, "points are all collinear (to rounding); a triangulation needs 2-D "
                                     "spread")):
        if bad.any():
            raise ValueError(f"{name}[{int(np.argmax(bad))}] {message}" if indexed else f"{name} {message}")


def check_sigma(sigma, name: str = "sigma") -> float:
    """Return ``sigma`` as a positive finite float or raise ValueError."""
    try:
        value = float(sigma)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {sigma!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {sigma!r}")
    if not MIN_MAGNITUDE <= value <= MAX_MAGNITUDE:
        check_sigma_range(np.array([value]), name)
    return value


def first_out_of_range(sd: np.ndarray) -> int | None:
    """The first row of positive standard deviations ``sd`` ((n,) or (n, k)) with one outside
    [``MIN_MAGNITUDE``, ``MAX_MAGNITUDE``], or None."""
    bad = (sd < MIN_MAGNITUDE) | (sd > MAX_MAGNITUDE)
    rows = np.flatnonzero(bad if bad.ndim == 1 else bad.any(axis=1))
    return int(rows[0]) if rows.size else None


def check_sigma_range(sigma: np.ndarray, name: str = "sigma") -> None:
    """Raise a one-line ValueError unless every positive σ lies in [``MIN_MAGNITUDE``, ``MAX_MAGNITUDE``]."""
    row = first_out_of_range(sigma)
    if row is not None:
        raise ValueError(f"{name} must lie in [{MIN_MAGNITUDE:g}, {MAX_MAGNITUDE:g}] (rescale the map's units), "
                         f"got {sigma[row]:g}")


def check_covariances(cov, n: int, name: str):
    """None, or per-landmark covariances as a (n, 2, 2) float array.

    Accepts (n,) variances per coordinate (isotropic) or (n, 2, 2)
    symmetric positive-definite matrices.
    """
    if cov is None:
        return None
    arr = float_array(cov, f"{name} must be (n,) variances or (n, 2, 2) covariances of real numbers")
    if arr.shape == (n,):
        if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
            raise ValueError(f"{name} must hold positive finite variances")
        arr = arr[:, None, None] * np.eye(2)
    elif arr.shape != (n, 2, 2):
        raise ValueError(f"{name} must have shape ({n},) or ({n}, 2, 2), one per landmark, got {arr.shape}")
    else:
        sym = np.abs(arr[:, 0, 1] - arr[:, 1, 0]) <= 1e-9 * np.abs(arr).max(axis=(1, 2))
        det = arr[:, 0, 0] * arr[:, 1, 1] - arr[:, 0, 1] * arr[:, 1, 0]
        if not (np.all(np.isfinite(arr)) and np.all(sym) and np.all(arr[:, 0, 0] > 0) and np.all(det > 0)):
            raise ValueError(f"{name} must hold symmetric positive-definite 2x2 covariances")
    check_sigma_range(np.sqrt(np.concatenate([arr[:, 0, 0], arr[:, 1, 1]])), f"{name}'s standard deviations")
    return arr


def check_rng(rng, name: str = "rng"):
    """``np.random.default_rng(rng)`` (None stays None), or a one-line ValueError naming the argument."""
    if rng is None:
        return None
    try:
        return np.random.default_rng(rng)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be None, a non-negative int, a SeedSequence or a Generator, "
                         f"got {rng!r}") from None
