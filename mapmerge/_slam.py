"""One agent's own SLAM solution with GTSAM's iSAM2 (optional extra ``[slam]``).

A robot solves SLAM as it drives, so each agent does too: pose by pose in
time order, its own odometry gives the new pose (guessed by composing the
odometry with the current estimate of the previous pose) and its own tree
sightings at that pose give bearing-range factors (a tree seen for the
first time is placed from that sighting); iSAM2 updates the solution after
every pose. Once the drive ends, a batch Levenberg-Marquardt refinement
starts from the incremental estimate and is kept only if it lowers the
graph's error. The trees' joint covariance (2m x 2m) comes from the
solution kept; ``datasets.slam_map`` derives per-tree covariances from it.

Solutions are cached on disk (``cache_dir()``), keyed by the data file's
contents, the agent's pose range and ``SETTINGS``: an ordinary directory of
``.npz`` files that can be deleted at any time.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

#: The solver's settings (GTSAM's own defaults for relinearisation) and the
#: anchor of the first pose. Part of the cache key.
SETTINGS = {
    "relinearize_threshold": 0.1,
    "relinearize_skip": 10,
    "batch_refinement": True,
    "prior_sigma": 1e-6,
    "version": 3,
}


def cache_dir() -> Path:
    """Where solved agent maps are kept: ``$MAPMERGE_CACHE`` or ``~/.cache/mapmerge/slam``."""
    root = os.environ.get("MAPMERGE_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "mapmerge" / "slam"


def _cache_key(path: Path, start: int, stop: int) -> str:
    digest = hashlib.sha256(path.read_bytes())
    digest.update(json.dumps({"start": start, "stop": stop, **SETTINGS}, sort_keys=True).encode())
    return digest.hexdigest()[:24]


def agent_map(log, start: int, stop: int, use_cache: bool = True):
    """Trees, their estimates and joint covariance for poses ``start..stop-1``.

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
    path = Path(log.path)
    cached = cache_dir() / f"{_cache_key(path, start, stop)}.npz"
    if use_cache and cached.is_file():
        with np.load(cached) as data:
            return data["ids"], data["points"], data["joint"]
    ids, points, joint = _solve(log, start, stop)
    if use_cache:
        cached.parent.mkdir(parents=True, exist_ok=True)
        tmp = cached.with_name(f".{cached.name}.{os.getpid()}.tmp.npz")
        np.savez(tmp, ids=ids, points=points, joint=joint)
        os.replace(tmp, cached)
    return ids, points, joint


def _solve(log, start: int, stop: int):
    try:
        import gtsam
    except ImportError as exc:
        raise ImportError("source='slam' needs GTSAM: pip install 'mapmerge[slam]'") from exc
    graph, _ = gtsam.load2D(str(log.path))
    pose_keys = [int(k) for k in log.pose_ids[start:stop]]
    step = {key: k for k, key in enumerate(pose_keys)}
    tree_of = {int(gtsam.Symbol("l", int(f)).key()): k for k, f in enumerate(log.tree_file_ids)}
    # Factors in time order: odometry into pose k, then the sightings taken at pose k.
    odometry, sightings = {}, {k: [] for k in range(len(pose_keys))}
    for i in range(graph.size()):
        factor = graph.at(i)
        keys = factor.keys()
        if isinstance(factor, gtsam.BetweenFactorPose2):
            if keys[0] in step and keys[1] in step:
                odometry[step[keys[1]]] = factor
        elif keys[0] in step:
            sightings[step[keys[0]]].append(factor)

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(SETTINGS["relinearize_threshold"])
    params.relinearizeSkip = SETTINGS["relinearize_skip"]
    isam = gtsam.ISAM2(params)
    full = gtsam.NonlinearFactorGraph()
    placed: set[int] = set()
    previous = gtsam.Pose2()
    for k, key in enumerate(pose_keys):
        new, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            new.add(gtsam.PriorFactorPose2(key, gtsam.Pose2(),
                                           gtsam.noiseModel.Isotropic.Sigma(3, SETTINGS["prior_sigma"])))
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
    estimate = isam.calculateEstimate()
    solution = estimate
    if SETTINGS["batch_refinement"]:
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
