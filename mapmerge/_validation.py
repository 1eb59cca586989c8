"""Input checks shared by the public functions (validation at the boundary only)."""

from __future__ import annotations

import math

import numpy as np


def check_points(points, name: str, min_points: int = 3, geometry: bool = True) -> np.ndarray:
    """Return ``points`` as a float (n, 2) array or raise a one-line ValueError.

    ``geometry`` adds the checks a triangulation needs: no duplicate points and
    not all points on one line.
    """
    try:
        arr = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an (n, 2) array of numbers") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (n, 2), got {arr.shape}")
    if arr.shape[0] < min_points:
        raise ValueError(f"{name} needs at least {min_points} points, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; all coordinates must be finite")
    if geometry:
        order = np.lexsort((arr[:, 1], arr[:, 0]))
        if np.any(np.all(arr[order[1:]] == arr[order[:-1]], axis=1)):
            raise ValueError(f"{name} contains duplicate points; landmarks must be distinct")
        # All on one line: every point's offset from the first is parallel to
        # the longest such offset (to 1e-12 of the squared extent).
        d = arr - arr[0]
        far = d[np.argmax(d[:, 0] ** 2 + d[:, 1] ** 2)]
        if np.max(np.abs(d[:, 0] * far[1] - d[:, 1] * far[0])) <= 1e-12 * (far[0] ** 2 + far[1] ** 2):
            raise ValueError(f"{name} points are all collinear; a triangulation needs 2-D spread")
    return arr


def check_sigma(sigma, name: str = "sigma") -> float:
    """Return ``sigma`` as a positive finite float or raise ValueError."""
    try:
        value = float(sigma)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {sigma!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {sigma!r}")
    return value


def check_covariances(cov, n: int, name: str):
    """None, or per-landmark covariances as a (n, 2, 2) float array.

    Accepts (n,) variances per coordinate (isotropic) or (n, 2, 2)
    symmetric positive-definite matrices.
    """
    if cov is None:
        return None
    try:
        arr = np.asarray(cov, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (n,) variances or (n, 2, 2) covariances") from None
    if arr.shape == (n,):
        if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
            raise ValueError(f"{name} must hold positive finite variances")
        return arr[:, None, None] * np.eye(2)
    if arr.shape != (n, 2, 2):
        raise ValueError(f"{name} must have shape ({n},) or ({n}, 2, 2), one per landmark, got {arr.shape}")
    sym = np.abs(arr[:, 0, 1] - arr[:, 1, 0]) <= 1e-9 * np.abs(arr).max(axis=(1, 2))
    det = arr[:, 0, 0] * arr[:, 1, 1] - arr[:, 0, 1] * arr[:, 1, 0]
    if not (np.all(np.isfinite(arr)) and np.all(sym) and np.all(arr[:, 0, 0] > 0) and np.all(det > 0)):
        raise ValueError(f"{name} must hold symmetric positive-definite 2x2 covariances")
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
