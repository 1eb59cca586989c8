"""95 % confidence intervals of the harness's rates and ratios.

A rate over trials (transform found, merge success, false merge) is a
binomial proportion: its Wilson score interval. A ratio of sums over
trials (P_D = ΣTP / Σ(TP + MD), precision, landmark recall) pools units
that are correlated within a trial (a trial's triangle pairs share its
maps), so its interval is the delta method's over trials, the sampled
units, not over the pooled counts.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm


def ratio_interval(x, y, level: float = 0.95) -> tuple[float, float]:
    """Normal interval of the ratio of sums Σx / Σy over n sampled units (the delta method:
    standard error √(Σ(x - R y)² / (n (n - 1))) / ȳ); NaN for fewer than 2 units or Σy = 0."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2 or y.sum() == 0:
        return float("nan"), float("nan")
    r = x.sum() / y.sum()
    half = norm.ppf(0.5 + level / 2) * np.sqrt(np.sum((x - r * y) ** 2) / (len(x) * (len(x) - 1))) / y.mean()
    return r - half, r + half



def wilson(successes, n, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval of a binomial proportion."""
    successes, n = np.asarray(successes, float), np.asarray(n, float)
    z = norm.ppf(0.5 + level / 2)
    p = successes / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    # Rounded: the formula leaves 1e-19 where the bound is exactly 0.
    return np.clip(np.round(centre - half, 12), 0.0, 1.0), np.clip(np.round(centre + half, 12), 0.0, 1.0)
