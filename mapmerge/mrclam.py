"""Five robots' own landmark maps from the UTIAS MR.CLAM data set (dataset 7).

The data (``mapmerge/data/mrclam/``, see its SOURCES.md) is one recording of
five robots driving for about 15 minutes among 15 surveyed landmarks. Each
robot logs its commanded forward and angular velocity and camera sightings
(range, bearing) of barcodes; a Vicon system gives every robot's true pose.
``datasets.mrclam`` (which reads the files, with ``datasets.load_mrclam``,
and assembles the maps) builds, for each robot, the landmark map that robot
would build alone: from its own odometry and its own landmark sightings,
in the frame of its own first pose, with no Vicon pose used in the solve.
This module holds the method: the calibration and the solver.

Calibration (``calibrate``), once per robot on its whole log against the
Vicon poses, as a robot's noise models would be measured before a mission:

- Odometry delay: the robots turn about a quarter of a second after the
  command is logged. The delay is the one on ``DELAY_GRID`` whose delayed
  commands, integrated over ``CALIBRATION_WINDOW`` seconds, best predict
  the Vicon heading change (least squares). Without it the heading error
  per window is 1.4-2 times as large (0.041-0.064 rad against
  0.025-0.037 rad for the five robots).
- Odometry noise: the RMS of the (forward, lateral, heading) error of the
  delayed, integrated commands over those windows against the Vicon motion,
  as a random walk: standard deviation per square-root second.
- Sighting noise: the range and bearing errors of the landmark sightings
  against the Vicon pose and the surveyed landmark, as robust standard
  deviations (1.4826 x the median absolute deviation): a few sightings are
  misread barcodes metres away and would inflate a plain standard deviation.
- Systematic landmark error: each landmark's sightings placed from the
  Vicon poses, their median against the surveyed position, RMS per
  coordinate over the landmarks. This part of a sighting's error is shared
  by all of a robot's sightings of one landmark (the camera's range error
  depends on the landmark and the viewing geometry), so it does not
  average away; the solve's noise model treats sightings as independent
  and would report covariances several times too small. Every landmark's
  covariance gets this variance added (``covs``, ``shape_covs``).

The solve (``solve_robot``), one robot at a time in time order: a pose at
each time the robot sighted landmarks, and at least every
``MAX_POSE_GAP`` seconds; between poses a ``BetweenFactorPose2`` with the
exactly integrated (arc by arc), delayed commands and the calibrated random
walk; each sighting a ``BearingRangeFactor2D`` with the calibrated noise
behind GTSAM's Huber M-estimator (``HUBER_K``), against misread barcodes;
a landmark seen for the first time is placed from that sighting. iSAM2
updates after every pose; at the end a batch Levenberg-Marquardt
refinement starting from the incremental estimate is kept if it lowers the
graph's error. The Huber kernel bounds a misread sighting's pull but does
not remove it, and a few dozen misreads (a barcode read as another
landmark's, metres away) bend a whole map: sightings whose range or
bearing error at the solution exceeds ``REJECTION_GATE`` calibrated
standard deviations are dropped and the batch solve is rerun (up to
``REJECTION_ROUNDS`` times). The first pose is held fixed (prior
``PRIOR_SIGMA``), so the map and its per-landmark marginal covariances are
in the frame of the robot's first pose. Sightings of other robots (subjects 1-5) are not used.

Barcodes are mapped to subjects through ``Barcodes.dat``; a sighting of a
barcode that is not listed is a misread and is dropped. Times are counted
from the start of the recording, the earliest Vicon time stamp of the five
robots; each robot's first pose is at its first odometry line.

Solves and calibrations are cached on disk with ``joblib.Memory`` under
``cache_dir() / "mrclam"`` (``$MAPMERGE_CACHE`` or ``~/.cache/mapmerge/slam``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._slam import cache_dir
from .alignment import wrap_angle

#: The robots of the recording (subjects 1-5) and the landmarks' subject numbers.
ROBOTS = (1, 2, 3, 4, 5)
LANDMARKS = tuple(range(6, 21))
#: Seconds over which the odometry is compared with the Vicon motion.
CALIBRATION_WINDOW = 1.0
#: Candidate odometry delays, seconds.
DELAY_GRID = np.round(np.arange(0.0, 0.61, 0.02), 2)
#: Longest stretch of odometry, seconds, between two poses of the graph,
#: and the shortest gap between a pose added for that and a sighting's pose.
MAX_POSE_GAP = 1.0
MIN_POSE_GAP = 0.05
#: Huber threshold in standard deviations (the usual 95 %-efficiency value).
HUBER_K = 1.345
#: Standard deviation of the prior holding the first pose (m, rad).
PRIOR_SIGMA = 1e-6
#: iSAM2's relinearisation (GTSAM's defaults).
RELINEARIZE_THRESHOLD = 0.1
RELINEARIZE_SKIP = 10
#: After the solve, sightings whose range or bearing error exceeds this many
#: calibrated standard deviations are dropped and the batch solve rerun, up
#: to ``REJECTION_ROUNDS`` times. On the whole logs 8 drops 19 of 16,067
#: sightings (robot 5's map: 0.035 m RMS against 0.110 m without); 5 drops
#: 121 and 4 drops 286, for maps whose RMS against the survey is within
#: 0.016 m of those at 8.
REJECTION_GATE = 8.0
REJECTION_ROUNDS = 3


def solver_settings() -> dict:
    """The solver's tunables (the module constants above, read when called), passed to ``solve_robot``
    so that the on-disk cache is keyed by them."""
    return {"max_pose_gap": MAX_POSE_GAP, "min_pose_gap": MIN_POSE_GAP, "huber_k": HUBER_K,
            "prior_sigma": PRIOR_SIGMA, "relinearize_threshold": RELINEARIZE_THRESHOLD,
            "relinearize_skip": RELINEARIZE_SKIP, "rejection_gate": REJECTION_GATE,
            "rejection_rounds": REJECTION_ROUNDS}
#: The MAD of a normal sample is this many times smaller than its standard deviation.
MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class RobotLog:
    """One robot's files, parsed.

    Attributes
    ----------
    robot : int
    odometry : (n, 3) ndarray
        Time (s), commanded forward (m/s) and angular (rad/s) velocity; of
        lines sharing a time stamp the last only (the command then in force).
    sightings : (m, 4) ndarray
        Time, landmark subject (6-20), range (m), bearing (rad).
    robot_sightings : (r, 4) ndarray
        The same for sightings of other robots (subjects 1-5), not used by the maps.
    misread : int
        Sightings of barcodes that ``Barcodes.dat`` does not list (dropped).
    groundtruth : (g, 4) ndarray
        Vicon time, x, y (m), heading (rad).
    """

    robot: int
    odometry: np.ndarray
    sightings: np.ndarray
    robot_sightings: np.ndarray
    misread: int
    groundtruth: np.ndarray


@dataclass(frozen=True)
class Recording:
    """The parsed data set: ``landmarks`` (15, 3) rows of subject, x, y (surveyed, m);
    ``start`` the recording's first Vicon time (s); ``robots`` the ``RobotLog`` of each robot asked for."""

    landmarks: np.ndarray
    start: float
    robots: dict
    path: Path


@dataclass(frozen=True)
class Calibration:
    """One robot's noise models, measured against the Vicon poses (see the module docstring).

    Attributes
    ----------
    delay : float
        Odometry delay, s.
    odometry_sigma : (3,) ndarray
        Forward, lateral, heading standard deviation per square-root second (m, m, rad).
    range_sigma, bearing_sigma : float
        Robust standard deviations of one sighting (m, rad).
    range_bias, bearing_bias : float
        Median sighting errors (reported, not corrected).
    landmark_sigma : float
        Systematic landmark error per coordinate (m), added to every landmark's covariance.
    heading_rms_undelayed : float
        RMS heading error per window without the delay, for comparison (rad).
    windows, sightings : int
        How many odometry windows and landmark sightings the numbers come from.
    """

    delay: float
    odometry_sigma: np.ndarray
    range_sigma: float
    bearing_sigma: float
    range_bias: float
    bearing_bias: float
    landmark_sigma: float
    heading_rms_undelayed: float
    windows: int
    sightings: int


@dataclass(frozen=True)
class MrclamTeam:
    """The robots' maps with ground truth, with the attributes of ``simulate.Team``.

    Attributes
    ----------
    robots : tuple of int
        Robot numbers, in the order of the lists below.
    maps : list of (n_i, 2) ndarray
        Each robot's landmarks in the frame of its first pose (m).
    covs : list of (n_i, 2, 2) ndarray
        Their marginal covariances, first pose held fixed, plus the
        calibrated systematic landmark error (``Calibration.landmark_sigma``).
    shape_covs : list of (n_i, 2, 2) ndarray
        The same with each map's rigid motion removed
        (``datasets.rigid_free_covariance``) before the systematic error is
        added: what is left once maps are aligned, the covariances to merge with.
    ids : list of (n_i,) int ndarray
        Landmark subject numbers (6-20), sorted.
    truth : (21, 2) ndarray
        Surveyed landmark positions in the world (Vicon) frame, row = subject
        number; rows 0-5 (no landmark) are NaN.
    first_poses : (N, 3) ndarray
        Each robot's true first pose (x, y, heading) in the world frame.
    theta, t : (N,), (N, 2) ndarray
        Rigid fit of each map onto the surveyed landmarks by id, in the
        convention map_i ≈ R(θ_i) world + t_i.
    sigma : (N,) ndarray
        RMS per-coordinate standard deviation of each map's entries (from ``shape_covs``).
    stranger : (N,) bool ndarray
        All False: every robot drove in the same arena.
    rms : (N,) ndarray
        Each map's RMS distance from the surveyed landmarks after the fit (m).
    rms_incremental : (N,) ndarray
        The same for the iSAM2 estimate before the batch refinement.
    sightings : (N,) int ndarray
        Landmark sightings in each robot's time span.
    rejected : (N,) int ndarray
        Of them, those the solve dropped as misread (``REJECTION_GATE``).
    calibrations : tuple of Calibration
    until_s : float or None
    """

    robots: tuple
    maps: list
    covs: list
    shape_covs: list
    ids: list
    truth: np.ndarray
    first_poses: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    sigma: np.ndarray
    stranger: np.ndarray
    rms: np.ndarray
    rms_incremental: np.ndarray
    sightings: np.ndarray
    rejected: np.ndarray
    calibrations: tuple
    until_s: float | None


def dead_reckon(odometry: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Poses (x, y, heading) at ``times`` from commands held until the next line, integrated exactly.

    The pose at ``odometry[0, 0]`` is the origin; ``times`` must be sorted
    and not earlier. Each piece of constant (v, ω) is an arc.
    """
    breaks = np.union1d(odometry[:, 0], times)
    line = np.searchsorted(odometry[:, 0], breaks[:-1], side="right") - 1
    v, w, dt = odometry[line, 1], odometry[line, 2], np.diff(breaks)
    heading = np.r_[0.0, np.cumsum(w * dt)]
    a, b = heading[:-1], heading[1:]
    straight = np.abs(w * dt) < 1e-9
    radius = v / np.where(straight, 1.0, w)
    dx = np.where(straight, v * dt * np.cos(a), radius * (np.sin(b) - np.sin(a)))
    dy = np.where(straight, v * dt * np.sin(a), radius * (np.cos(a) - np.cos(b)))
    poses = np.column_stack([np.r_[0.0, np.cumsum(dx)], np.r_[0.0, np.cumsum(dy)], heading])
    return poses[np.searchsorted(breaks, times)]


def relative_poses(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose b in the frame of pose a, row by row: (dx, dy, dθ)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    d = b[:, :2] - a[:, :2]
    return np.column_stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], wrap_angle(b[:, 2] - a[:, 2])])


def vicon_poses(groundtruth: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Vicon poses linearly interpolated at ``times`` (heading unwrapped first)."""
    heading = np.unwrap(groundtruth[:, 3])
    return np.column_stack([np.interp(times, groundtruth[:, 0], groundtruth[:, c]) for c in (1, 2)]
                           + [np.interp(times, groundtruth[:, 0], heading)])


def delayed(odometry: np.ndarray, delay: float) -> np.ndarray:
    """Commands taking effect ``delay`` seconds after they are logged (standing still until the first does)."""
    return np.r_[[[odometry[0, 0], 0.0, 0.0]], odometry + [delay, 0.0, 0.0]]


def sighting_errors(log: RobotLog, landmarks: np.ndarray):
    """Range and bearing errors of each landmark sighting against the Vicon pose and the surveyed landmark."""
    where = dict(zip(landmarks[:, 0].astype(int).tolist(), landmarks[:, 1:]))
    target = np.array([where[int(s)] for s in log.sightings[:, 1]]).reshape(-1, 2)
    pose = vicon_poses(log.groundtruth, log.sightings[:, 0])
    d = target - pose[:, :2]
    range_err = log.sightings[:, 2] - np.hypot(d[:, 0], d[:, 1])
    bearing_err = wrap_angle(log.sightings[:, 3] - (np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2]))
    return range_err, bearing_err


def _robust_sigma(e: np.ndarray) -> float:
    return float(MAD_TO_SIGMA * np.median(np.abs(e - np.median(e))))


def calibrate(log: RobotLog, landmarks: np.ndarray, window: float = CALIBRATION_WINDOW,
              delays: np.ndarray = DELAY_GRID) -> Calibration:
    """Measure one robot's odometry delay and noise models against the Vicon poses (module docstring).

    ``window`` (s) and ``delays`` (s) default to ``CALIBRATION_WINDOW`` and ``DELAY_GRID``."""
    odo = log.odometry
    start = np.arange(odo[0, 0], odo[-1, 0] - window, window)
    n = len(start)
    if n < 10 or len(log.sightings) < 10:
        raise ValueError(f"robot {log.robot}: too little data to calibrate ({n} odometry windows, "
                           f"{len(log.sightings)} landmark sightings)")
    times = np.r_[start, start + window]
    truth = vicon_poses(log.groundtruth, times)
    true_motion = relative_poses(truth[:n], truth[n:])

    def errors(delay):
        poses = dead_reckon(delayed(odo, delay), times)
        e = true_motion - relative_poses(poses[:n], poses[n:])
        e[:, 2] = wrap_angle(e[:, 2])
        return e

    heading_mse = [np.mean(errors(d)[:, 2] ** 2) for d in delays]
    delay = float(delays[int(np.argmin(heading_mse))])
    e = errors(delay)
    range_err, bearing_err = sighting_errors(log, landmarks)
    pose = vicon_poses(log.groundtruth, log.sightings[:, 0])
    bearing = pose[:, 2] + log.sightings[:, 3]
    placed = pose[:, :2] + log.sightings[:, 2:3] * np.column_stack([np.cos(bearing), np.sin(bearing)])
    subjects = np.unique(log.sightings[:, 1])
    median = np.array([np.median(placed[log.sightings[:, 1] == s], axis=0) for s in subjects])
    surveyed = landmarks[np.searchsorted(landmarks[:, 0], subjects), 1:]
    return Calibration(
        landmark_sigma=float(np.sqrt(np.mean((median - surveyed) ** 2))),
        delay=delay, odometry_sigma=np.sqrt(np.mean(e**2, axis=0) / window),
        range_sigma=_robust_sigma(range_err), bearing_sigma=_robust_sigma(bearing_err),
        range_bias=float(np.median(range_err)), bearing_bias=float(np.median(bearing_err)),
        heading_rms_undelayed=float(np.sqrt(heading_mse[0])), windows=n, sightings=len(range_err),
    )


def pose_times(first: float, end: float, sighting_times: np.ndarray, max_gap: float = MAX_POSE_GAP,
               min_gap: float = MIN_POSE_GAP) -> np.ndarray:
    """The graph's pose times: the first pose, every sighting time, and a grid of ``MAX_POSE_GAP``
    up to ``end``, where a grid time within ``MIN_POSE_GAP`` of another pose is left out (it would
    add only a nearly zero-length, ill-conditioned step)."""
    required = np.union1d(sighting_times, [first])
    grid = np.r_[np.arange(first, end, max_gap), end]
    after = np.searchsorted(required, grid)
    gap = np.minimum(np.abs(grid - required[np.maximum(after - 1, 0)]),
                     np.abs(required[np.minimum(after, len(required) - 1)] - grid))
    return np.union1d(required, grid[gap >= min_gap])


def solve_robot(odometry: np.ndarray, sightings: np.ndarray, end_time: float, delay: float,
                odometry_sigma: np.ndarray, sighting_sigma: np.ndarray, settings: dict) -> dict:
    """One robot's landmark map by iSAM2 (then a batch refinement), in the frame of its first pose.

    Parameters
    ----------
    odometry : (n, 3) ndarray
        The robot's odometry lines (time, v, ω); the first pose is at ``odometry[0, 0]``.
    sightings : (m, 4) ndarray
        Landmark sightings (time, subject, range, bearing) between the first pose and ``end_time``.
    end_time : float
        The last pose's time (not after the last odometry line).
    delay, odometry_sigma, sighting_sigma
        The calibration: delay (s), (forward, lateral, heading) σ per √s,
        (bearing, range) σ of one sighting.
    settings : dict
        The tunables, ``solver_settings()``.

    Returns
    -------
    dict
        ``ids`` (k,), ``points`` (k, 2), ``joint`` (2k, 2k) joint marginal
        covariance of the landmarks, ``incremental`` (k, 2) the iSAM2
        estimate before refinement, ``poses`` the number of poses.
    """
    try:
        import gtsam
    except ImportError as exc:
        raise ImportError("the MR.CLAM maps need GTSAM: pip install 'mapmerge[slam]'") from exc
    times = pose_times(odometry[0, 0], end_time, sightings[:, 0], settings["max_pose_gap"], settings["min_pose_gap"])
    poses = dead_reckon(delayed(odometry, delay), times)
    steps = relative_poses(poses[:-1], poses[1:])
    step_sigma = np.maximum(odometry_sigma[None, :] * np.sqrt(np.diff(times))[:, None], settings["prior_sigma"])
    sighting_noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(settings["huber_k"]),
                                                    gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sighting_sigma, float)))
    full, motion, seen, estimate = _incremental_solve(times, steps, step_sigma, sightings, sighting_noise, settings)
    refined = gtsam.LevenbergMarquardtOptimizer(full, estimate).optimize()
    solution = refined if full.error(refined) < full.error(estimate) else estimate
    full, solution, keep = _reject_misreads(full, solution, (motion, seen), sightings, len(times), sighting_sigma,
                                            settings)
    ids = np.unique(sightings[keep, 1]).astype(np.int64)
    keys = gtsam.KeyVector()
    for subject in ids:
        keys.append(_landmark_key(subject))
    # The joint marginal's blocks come in key order, which for one symbol letter is the ids' order.
    joint = gtsam.Marginals(full, solution).jointMarginalCovariance(keys).fullMatrix()
    return {
        "ids": ids,
        "points": np.array([solution.atPoint2(_landmark_key(s)) for s in ids]).reshape(-1, 2),
        "incremental": np.array([estimate.atPoint2(_landmark_key(s)) for s in ids]).reshape(-1, 2),
        "joint": joint,
        "poses": len(times),
        "rejected": int(np.sum(~keep)),
    }


def _pose_key(i) -> int:
    import gtsam

    return gtsam.symbol("x", int(i))


def _landmark_key(subject) -> int:
    import gtsam

    return gtsam.symbol("l", int(subject))


def _incremental_solve(times, steps, step_sigma, sightings, sighting_noise, settings: dict):
    """iSAM2 pose by pose at ``times`` (odometry ``steps`` with σ ``step_sigma``; each of ``sightings`` at
    its pose, a landmark seen for the first time placed from that sighting).

    Returns the whole factor graph, its prior and odometry factors, its sighting factors (in the
    sightings' order) and iSAM2's estimate at the end.
    """
    import gtsam

    at_pose = np.searchsorted(times, sightings[:, 0])
    by_pose = np.searchsorted(at_pose, np.arange(len(times) + 1))
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(settings["relinearize_threshold"])
    params.relinearizeSkip = settings["relinearize_skip"]
    isam = gtsam.ISAM2(params)
    full = gtsam.NonlinearFactorGraph()
    motion, seen = [], []  # the prior and odometry factors; the sighting factors in the sightings' order
    placed: list[int] = []
    current = gtsam.Pose2()
    for i in range(len(times)):
        new, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if i == 0:
            motion.append(gtsam.PriorFactorPose2(_pose_key(0), current,
                                                 gtsam.noiseModel.Isotropic.Sigma(3, settings["prior_sigma"])))
        else:
            step = gtsam.Pose2(*steps[i - 1])
            motion.append(gtsam.BetweenFactorPose2(_pose_key(i - 1), _pose_key(i), step,
                                                   gtsam.noiseModel.Diagonal.Sigmas(step_sigma[i - 1])))
            current = current.compose(step)
        new.add(motion[-1])
        values.insert(_pose_key(i), current)
        for _, subject, rng, bearing in sightings[by_pose[i]:by_pose[i + 1]]:
            seen.append(gtsam.BearingRangeFactor2D(_pose_key(i), _landmark_key(subject), gtsam.Rot2(bearing), rng,
                                                   sighting_noise))
            new.add(seen[-1])
            if int(subject) not in placed:
                placed.append(int(subject))
                values.insert(_landmark_key(subject),
                              current.transformFrom(gtsam.Point2(rng * np.cos(bearing), rng * np.sin(bearing))))
        isam.update(new, values)
        full.push_back(new)
        current = isam.calculateEstimatePose2(_pose_key(i))
    return full, motion, seen, isam.calculateEstimate()


def _reject_misreads(full, solution, factors: tuple, sightings, n_poses: int, sighting_sigma, settings: dict):
    """Drop the sightings beyond ``REJECTION_GATE`` σ at the solution and solve again, up to
    ``REJECTION_ROUNDS`` times. ``factors``: the (motion, sighting) factors of ``full``.

    Returns the last factor graph, its solution and which sightings are kept.
    """
    import gtsam

    motion, seen = factors
    # Misread barcodes put a sighting metres from its landmark; the Huber kernel only bounds their pull.
    keep = np.ones(len(seen), bool)
    for _ in range(settings["rejection_rounds"]):
        error = np.array([f.unwhitenedError(solution) for f in seen]).reshape(-1, 2)
        bad = keep & np.any(np.abs(error) > settings["rejection_gate"] * np.asarray(sighting_sigma, float), axis=1)
        if not bad.any():
            break
        keep &= ~bad
        full = gtsam.NonlinearFactorGraph()
        for factor in motion + [f for f, k in zip(seen, keep) if k]:
            full.add(factor)
        start = gtsam.Values()
        for i in range(n_poses):
            start.insert(_pose_key(i), solution.atPose2(_pose_key(i)))
        for subject in np.unique(sightings[keep, 1]):
            start.insert(_landmark_key(subject), solution.atPoint2(_landmark_key(subject)))
        solution = gtsam.LevenbergMarquardtOptimizer(full, start).optimize()
    return full, solution, keep


def memory():
    """The on-disk cache of calibrations and solves (``joblib.Memory`` under ``cache_dir() / "mrclam"``)."""
    try:
        import joblib
    except ImportError as exc:
        raise ImportError("the MR.CLAM maps' cache needs joblib: pip install 'mapmerge[slam]'") from exc
    return joblib.Memory(cache_dir() / "mrclam", verbose=0)
