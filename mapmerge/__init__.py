"""mapmerge: match and merge stochastic landmark maps from independent robots.

Implements the closed-form GLRT between Delaunay triangles in Groth order,
bipartite matching by the assignment LP and the closed-form maximum-likelihood
combined map of the seed paper, plus the ground truth and metrics to measure
them. See DESIGN.md for the mathematics and conventions.

>>> import mapmerge as mm
>>> sc = mm.simulate.make_pair(n_landmarks=100, overlap=0.75, snr_db=40, rng=0)
>>> res = mm.merge_maps(sc.p, sc.q, sc.sigma)
"""

from . import metrics, simulate
from .combining import CombinedMap
from .matching import log_tau_from_chi2, resolve_log_tau
from .merging import MergeResult, merge_maps
from .statistic import Alignment, align, glrt, rotation, wrap_angle
from .triangles import Triangles, triangulate

__all__ = [
    "Alignment",
    "CombinedMap",
    "MergeResult",
    "Triangles",
    "align",
    "glrt",
    "log_tau_from_chi2",
    "merge_maps",
    "metrics",
    "resolve_log_tau",
    "rotation",
    "simulate",
    "triangulate",
    "wrap_angle",
]
__version__ = "0.1.0"
