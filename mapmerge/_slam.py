"""One agent's own SLAM solution with GTSAM (optional extra ``[slam]``).

The agent keeps the odometry between its own poses and its own tree
observations from ``gtsam.load2D`` (which turns each Cartesian sighting into
a bearing-range factor), anchors its first pose at the origin, optimises with
Levenberg-Marquardt and reads each tree's marginal covariance.
"""

from __future__ import annotations

import numpy as np


def agent_map(log, start: int, stop: int):
    """Trees, their estimates and marginal covariances for poses ``start..stop-1``.

    Returns
    -------
    ids : (m,) int ndarray
        Tree ids (rows of the reference tree map), sorted.
    points : (m, 2) ndarray
        Tree estimates in the frame of pose ``start``.
    cov : (m, 2, 2) ndarray
        Marginal covariances.
    """
    try:
        import gtsam
    except ImportError as exc:
        raise ImportError("source='slam' needs GTSAM: pip install -e '.[slam]'") from exc
    graph, initial = gtsam.load2D(str(log.path))
    poses = {int(k) for k in log.pose_ids[start:stop]}
    first = int(log.pose_ids[start])
    tree_of = {int(gtsam.Symbol("l", int(f)).key()): k for k, f in enumerate(log.tree_file_ids)}

    agent = gtsam.NonlinearFactorGraph()
    seen_trees: set[int] = set()
    for i in range(graph.size()):
        factor = graph.at(i)
        keys = factor.keys()
        if isinstance(factor, gtsam.BetweenFactorPose2):
            if keys[0] in poses and keys[1] in poses:
                agent.add(factor)
        elif keys[0] in poses:
            agent.add(factor)
            seen_trees.add(keys[1])
    agent.add(gtsam.PriorFactorPose2(first, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))

    # Start from the file's dead-reckoning values, rebased on the first pose.
    origin = initial.atPose2(first)
    values = gtsam.Values()
    for key in poses:
        values.insert(key, origin.between(initial.atPose2(key)))
    for key in seen_trees:
        values.insert(key, origin.transformTo(initial.atPoint2(key)))
    result = gtsam.LevenbergMarquardtOptimizer(agent, values).optimize()
    marginals = gtsam.Marginals(agent, result)

    keys = sorted(seen_trees, key=lambda k: tree_of[k])
    ids = np.array([tree_of[k] for k in keys], dtype=np.intp)
    points = np.array([result.atPoint2(k) for k in keys])
    cov = np.array([marginals.marginalCovariance(k) for k in keys])
    return ids, points, cov
