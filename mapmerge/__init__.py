"""mapmerge: match and merge stochastic landmark maps from independent robots.

Implements the closed-form GLRT between Delaunay triangles in Groth order,
bipartite matching by the assignment LP and the closed-form maximum-likelihood
combined map of B. Jones, M. Campbell and L. Tong ("Maximum likelihood
combining of stochastic maps"; journal version "Maximum likelihood fusion
of stochastic maps", arXiv:1303.6170), methods that go beyond it, and the
ground truth and metrics to measure them.

One module per stage: ``triangles``, ``statistic`` (GLRT), ``alignment``
(transform fits), ``assignment`` (the LP), ``matching`` (τ and the
triangle-matching driver), ``correspondence`` (landmark correspondences by
vote), ``combining`` (eq. 15), ``association`` (landmark association under a
transform), ``consensus`` (consensus verification), ``baselines``,
``result`` (what a merge returns), ``merging`` (the method registry and
``merge_maps``), ``group`` (``merge_many``: N maps), ``simulate``,
``metrics``, ``datasets``. Every stage works on a batch of map pairs; the
one-pair functions are its batch of one.

>>> import mapmerge as mm
>>> sc = mm.simulate.make_pair(n_landmarks=100, overlap=0.75, snr_db=40, rng=0)
>>> res = mm.merge_maps(sc.p, sc.q, sc.sigma)
"""

from importlib.metadata import PackageNotFoundError, version

from . import exhaustive, metrics, simulate
from .alignment import Alignment, align, rotation, wrap_angle
from .combining import CombinedMap
from .group import GroupMerge, merge_many
from .mapfiles import LandmarkMap, MapFileError, read_map, write_map
from .matching import log_tau_from_chi2, resolve_log_tau
from .merging import METHODS, ResidualMatch, merge_batch, merge_maps, residual_match
from .result import MergeBatch, MergeResult
from .statistic import glrt
from .triangles import Triangles, triangulate

__all__ = [
    "Alignment",
    "CombinedMap",
    "GroupMerge",
    "LandmarkMap",
    "MapFileError",
    "METHODS",
    "MergeBatch",
    "MergeResult",
    "ResidualMatch",
    "Triangles",
    "align",
    "exhaustive",
    "glrt",
    "log_tau_from_chi2",
    "merge_batch",
    "merge_maps",
    "merge_many",
    "read_map",
    "write_map",
    "metrics",
    "residual_match",
    "resolve_log_tau",
    "rotation",
    "simulate",
    "triangulate",
    "wrap_angle",
]
try:
    __version__ = version("mapmerge")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "unknown"

#: Modules loaded on first use as ``mapmerge.<name>``: each imports what only it needs.
_LAZY_MODULES = ("datasets", "plotting", "search", "consensus", "baselines", "cli")


def __getattr__(name):
    if name in _LAZY_MODULES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
