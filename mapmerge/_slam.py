"""One agent's own SLAM solution with GTSAM's iSAM2 (optional extra ``[slam]``).

A robot solves SLAM as it drives, so each agent does too: pose by pose in
time order, its own odometry gives the new pose (guessed by composing the
odometry with the current estimate of the previous pose) and its own tree
sightings at that pose give bearing-range factors (a tree seen for the
first time is placed from that sighting); iSAM2 updates the solution after
every pose.

A sighting's noise is the covariance its line of the data file gives (x, y
in the robot frame; 0.4 m² per axis), carried to bearing and range to first
order. GTSAM's ``load2D``, which reads the odometry, replaces it with a rule
of its own (bearing standard deviation √(0.4 / 10) = 0.2 rad whatever the
range: the file's value taken as the noise at 10 m), which lets far trees
swing metres sideways. On the whole drive the file's noise puts the trees
0.13 m (RMSE) from the reference map, load2D's 0.57 m; reading the file's
numbers as information instead of covariance gives 0.96 m.

Once the drive ends, a batch Levenberg-Marquardt refinement starts from
the incremental estimate and is kept only if it lowers the graph's error.
The trees' joint covariance (2m x 2m) comes from the solution kept;
``datasets.slam_map`` derives per-tree covariances from it.

Solutions are cached on disk with ``joblib.Memory`` under
``cache_dir() / "victoria_park"``, keyed by the data file's contents, the
log's parsed sightings, the agent's pose range, the solver's settings, the
source of this module and the GTSAM and numpy versions: a directory that
can be deleted at any time.
"""

from __future__ import annotations

import hashlib
import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

#: The solver's settings (GTSAM's own defaults for relinearisation) and the
#: anchor of the first pose. Part of the cache key. ``sighting_noise``:
#: ``"file"`` (each sighting's covariance from its line of the data file) or
#: ``"load2d"`` (GTSAM ``load2D``'s rule, see the module docstring).
#: ``sighting_kernel``: ``None`` (Gaussian sightings) or ``"huber"`` (GTSAM's
#: Huber M-estimator at ``HUBER_K`` standard deviations, against wrongly
#: associated sightings).
SETTINGS = {
    "relinearize_threshold": 0.1,
    "relinearize_skip": 10,
    "batch_refinement": True,
    "sighting_noise": "file",
    "sighting_kernel": None,
    "prior_sigma": 1e-6,
    "version": 4,
}

#: Huber threshold in standard deviations (the usual 95 %-efficiency value).
HUBER_K = 1.345


def solver_settings(overrides=None) -> dict:
    """``SETTINGS`` with ``overrides`` applied; a one-line ValueError names a bad key or value."""
    overrides = dict(overrides or {})
    tunable = sorted(set(SETTINGS) - {"version"})
    unknown = sorted(set(overrides) - set(tunable))
    if unknown:
        raise ValueError(f"solver settings must be among {tunable}, got {unknown}")
    settings = {**SETTINGS, **overrides}
    for key in ("relinearize_threshold", "prior_sigma"):
        value = settings[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < np.inf:
            raise ValueError(f"{key} must be a positive number, got {value!r}")
    skip = settings["relinearize_skip"]
    if isinstance(skip, bool) or not isinstance(skip, (int, np.integer)) or skip < 1:
        raise ValueError(f"relinearize_skip must be an integer >= 1, got {skip!r}")
    if not isinstance(settings["batch_refinement"], bool):
        raise ValueError(f"batch_refinement must be True or False, got {settings['batch_refinement']!r}")
    if settings["sighting_noise"] not in ("file", "load2d"):
        raise ValueError(f"sighting_noise must be 'file' or 'load2d', got {settings['sighting_noise']!r}")
    if settings["sighting_kernel"] not in (None, "huber"):
        raise ValueError(f"sighting_kernel must be None or 'huber', got {settings['sighting_kernel']!r}")
    # Plain Python numbers: the settings are part of the cache key.
    return {**settings, "relinearize_threshold": float(settings["relinearize_threshold"]),
            "relinearize_skip": int(skip), "prior_sigma": float(settings["prior_sigma"])}


def bearing_range_covariance(xy: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance of (bearing, range) of a point ``xy`` in the robot frame whose covariance is ``cov``.

    First order: ``J cov Jᵀ`` with J the Jacobian of (atan2(y, x), |xy|);
    an isotropic σ² I gives diag(σ² / r², σ²).
    """
    x, y = xy
    r2 = x * x + y * y
    J = np.array([[-y / r2, x / r2], [x / np.sqrt(r2), y / np.sqrt(r2)]])
    return J @ cov @ J.T


def cache_dir() -> Path:
    """Where solved agent maps are kept: ``$MAPMERGE_CACHE`` or ``~/.cache/mapmerge/slam``."""
    root = os.environ.get("MAPMERGE_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "mapmerge" / "slam"


def agent_map(log, start: int, stop: int, use_cache: bool = True, settings=None):
    """Trees, their estimates and joint covariance for poses ``start..stop-1``.

    ``settings``: overrides of ``SETTINGS`` (``solver_settings`` checks them).

    Returns
    -------
    ids : (m,) int ndarray
        Tree ids (rows of the reference tree map), sorted.
    points : (m, 2) ndarray
        Tree estimates in the frame of pose ``start``.
    joint : (2m, 2m) ndarray
        Joint covariance of the trees' coordinates (x_0, y_0, x_1, ...),
        the first pose held fixed.
    """
    settings = solver_settings(settings)
    if not use_cache:
        return _solve(log, start, stop, settings)
    try:
        import joblib
    except ImportError as exc:
        raise ImportError("the SLAM solves' cache needs joblib: pip install 'mapmerge[slam]'") from exc
    cached = joblib.Memory(cache_dir() / "victoria_park", verbose=0).cache(_keyed_solve, ignore=["log"])
    data = hashlib.sha256(Path(log.path).read_bytes()).hexdigest()
    sightings = (log.pose_ids, log.tree_file_ids, log.obs_pose, log.obs_tree, log.obs_xy, log.obs_cov)
    return cached(log, data, sightings, start, stop, settings, _code_versions())


def _keyed_solve(log, data: str, sightings: tuple, start: int, stop: int, settings: dict, versions: dict):
    """``_solve``, with what its result depends on besides ``log`` itself as arguments (the cache's key):
    ``data`` the data file's digest (GTSAM reads the file), ``sightings`` the log's parsed arrays that the
    solve reads, and ``versions`` the solver's code and libraries (``_code_versions``)."""
    return _solve(log, start, stop, settings)


def _code_versions() -> dict:
    """This module's source digest and the GTSAM and numpy versions: a solve cached under others is stale."""
    try:
        gtsam_version = version("gtsam")
    except PackageNotFoundError:
        gtsam_version = None  # _solve names the missing extra
    return {"source": hashlib.sha256(Path(__file__).read_bytes()).hexdigest(), "gtsam": gtsam_version,
            "numpy": np.__version__}


def _solve(log, start: int, stop: int, settings: dict):
    try:
        import gtsam
    except ImportError as exc:
        raise ImportError("source='slam' needs GTSAM: pip install 'mapmerge[slam]'") from exc
    pose_keys = [int(k) for k in log.pose_ids[start:stop]]
    tree_key = [int(gtsam.Symbol("l", int(f)).key()) for f in log.tree_file_ids]
    tree_of = {key: k for k, key in enumerate(tree_key)}
    odometry, sightings = _factors_by_pose(log, pose_keys, tree_key, settings)
    full, estimate, placed = _incremental_solve(pose_keys, odometry, sightings, settings)
    solution = estimate
    if settings["batch_refinement"]:
        refined = gtsam.LevenbergMarquardtOptimizer(full, estimate).optimize()
        if full.error(refined) < full.error(estimate):
            solution = refined
    trees = sorted(placed, key=lambda t: tree_of[t])
    ids = np.array([tree_of[t] for t in trees], dtype=np.intp)
    points = np.array([solution.atPoint2(t) for t in trees])
    keys = gtsam.KeyVector()
    for tree in trees:
        keys.append(tree)
    # GTSAM orders the joint marginal's blocks by key, not as asked: put them in the trees' order.
    blocks = np.argsort(np.argsort(np.array(trees, dtype=np.uint64)))
    rows = (2 * blocks[:, None] + np.arange(2)).ravel()
    joint = gtsam.Marginals(full, solution).jointMarginalCovariance(keys).fullMatrix()[np.ix_(rows, rows)]
    return ids, points, joint


def _factors_by_pose(log, pose_keys: list, tree_key: list, settings: dict):
    """The data file's factors of poses ``pose_keys``, as GTSAM's ``load2D`` reads them, by pose:
    the odometry into pose k and the bearing-range sightings taken at pose k (their noise per ``settings``)."""
    import gtsam

    graph, _ = gtsam.load2D(str(log.path))
    step = {key: k for k, key in enumerate(pose_keys)}
    kernel = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K) if settings["sighting_kernel"] == "huber" else None
    # Factors in time order: odometry into pose k, then the sightings taken at pose k.
    odometry, sightings = {}, {k: [] for k in range(len(pose_keys))}
    n_sighting = -1  # load2D keeps the file's order: its n-th sighting is the log's
    for i in range(graph.size()):
        factor = graph.at(i)
        keys = factor.keys()
        if isinstance(factor, gtsam.BetweenFactorPose2):
            if keys[0] in step and keys[1] in step:
                odometry[step[keys[1]]] = factor
            continue
        n_sighting += 1
        if keys[1] != tree_key[log.obs_tree[n_sighting]] or keys[0] != log.pose_ids[log.obs_pose[n_sighting]]:
            raise RuntimeError(f"load2D's sighting {n_sighting} is not the data file's")
        if keys[0] not in step:
            continue
        noise = factor.noiseModel()
        if settings["sighting_noise"] == "file":
            noise = gtsam.noiseModel.Gaussian.Covariance(
                bearing_range_covariance(log.obs_xy[n_sighting], log.obs_cov[n_sighting]))
        if kernel is not None:
            noise = gtsam.noiseModel.Robust.Create(kernel, noise)
        m = factor.measured()
        sightings[step[keys[0]]].append(gtsam.BearingRangeFactor2D(keys[0], keys[1], m.bearing(), m.range(), noise))
    return odometry, sightings


def _incremental_solve(pose_keys: list, odometry: dict, sightings: dict, settings: dict):
    """iSAM2 pose by pose (a tree seen for the first time placed from that sighting): the whole
    factor graph, iSAM2's estimate at the end and the keys of the trees placed."""
    import gtsam

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(settings["relinearize_threshold"])
    params.relinearizeSkip = settings["relinearize_skip"]
    isam = gtsam.ISAM2(params)
    full = gtsam.NonlinearFactorGraph()
    placed: set[int] = set()
    previous = gtsam.Pose2()
    for k, key in enumerate(pose_keys):
        new, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            new.add(gtsam.PriorFactorPose2(key, gtsam.Pose2(),
                                           gtsam.noiseModel.Isotropic.Sigma(3, settings["prior_sigma"])))
            guess = gtsam.Pose2()
        else:
            factor = odometry[k]
            new.add(factor)
            guess = previous.compose(factor.measured())
        values.insert(key, guess)
        for factor in sightings[k]:
            new.add(factor)
            tree = factor.keys()[1]
            if tree not in placed:
                m = factor.measured()
                b, r = m.bearing().theta(), m.range()
                values.insert(tree, guess.transformFrom(gtsam.Point2(r * np.cos(b), r * np.sin(b))))
                placed.add(tree)
        isam.update(new, values)
        full.push_back(new)
        previous = isam.calculateEstimatePose2(key)
    return full, isam.calculateEstimate(), placed
