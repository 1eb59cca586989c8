"""Real landmark maps: two agents' maps of Victoria Park (Sydney).

The data (``mapmerge/data/victoria_park/``, see its SOURCES.md) is the iSAM
observation log of a vehicle driving among 151 trees, the reference
(optimised) trajectory and the reference tree map. ``victoria_park`` splits
the drive at a pose index into agent p (the poses before) and agent q (the
poses from there on). Each agent builds its own map, in the frame of its own
first pose, from its own observations only:

- ``source="reference"``: every observation is placed with the reference
  pose it was taken from and each tree's observations are averaged. The
  per-tree covariance is the pooled scatter of one observation, divided by
  the tree's number of observations.
- ``source="slam"``: the agent solves its own SLAM problem with GTSAM
  (optional extra ``[slam]``) from its own odometry and tree observations,
  anchored at its first pose, and reports each tree's covariance with the
  map's rigid motion removed (``slam_map``: what is left once maps are
  aligned).

Pose and landmark ids share one number space in the log; poses are counted
in the order they appear in the odometry chain. The reference tree map's row
k is the k-th distinct tree id in order of first appearance, and k is the
landmark id used for ground truth.

The log's own data association splits a few trees: four pairs of tree ids
lie 0.15-0.83 m apart in the reference map (ids 9/50, 115/117, 3/19, 4/18;
trunks cannot stand that close), so an agent's map can hold the same trunk
twice. Ground truth of an association is therefore the physical tree
(``physical_trees``: ids closer than ``SAME_TREE_RADIUS`` are one tree),
not the raw id; the rigid fits by id (``map_quality``, the fit-by-ids
truth) use raw ids, which are unambiguous there.

``mrclam`` gives five robots' maps of the MR.CLAM data set (dataset 7,
bundled in ``mapmerge/data/mrclam/``), each solved by the robot alone;
``mapmerge.mrclam`` holds the method.
"""

from __future__ import annotations

import functools
import gzip
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import mrclam as mrclam_slam
from .alignment import align_pairs, rotate, rotation, wrap_angle
from .merging import pooled_sigma

#: Where the bundled copy of the data lives.
DATA_DIR = Path(__file__).resolve().parent / "data" / "victoria_park"
LOG_FILE = "victoria_park.txt"
TRAJECTORY_FILE = "ISAM2_GT_victoriaPark.txt"
TREES_FILE = "ISAM2_GT_victoriaPark_lm.txt"
SOURCES = ("reference", "slam")
#: The cut of the project's tests and README: 82 and 135 trees, 66 common.
DEFAULT_CUT = 3483
#: Tree ids whose reference positions are closer than this (metres) are one
#: physical tree. The next-closest pair of ids is 1.32 m apart.
SAME_TREE_RADIUS = 1.0


class DatasetError(ValueError):
    """A data file is missing or malformed."""


@dataclass(frozen=True)
class VictoriaParkLog:
    """The parsed observation log and reference solution.

    Attributes
    ----------
    odometry : (P-1, 3) ndarray
        Relative motion (dx, dy, dθ) from pose i to pose i+1 (pose indices).
    odometry_cov : (P-1, 6) ndarray
        The upper triangle of each odometry line's covariance (xx, xy, xθ,
        yy, yθ, θθ), as in the file.
    obs_pose : (M,) int ndarray
        Pose index of each tree observation.
    obs_tree : (M,) int ndarray
        Tree id (row of the reference tree map) of each observation.
    obs_xy : (M, 2) ndarray
        The tree in the robot frame, metres.
    obs_cov : (M, 2, 2) ndarray
        Its covariance in the robot frame, m² (0.4 I on every line of the
        bundled file: a standard deviation of 0.63 m per axis).
    trajectory : (P_ref, 3) ndarray
        Reference pose (x, y, θ) of pose index i.
    trees : (151, 2) ndarray
        Reference tree positions in the frame of pose 0.
    pose_ids : (P,) int ndarray
        File id of pose index i.
    tree_file_ids : (151,) int ndarray
        File id of tree id k.
    """

    odometry: np.ndarray
    odometry_cov: np.ndarray
    obs_pose: np.ndarray
    obs_tree: np.ndarray
    obs_xy: np.ndarray
    obs_cov: np.ndarray
    trajectory: np.ndarray
    trees: np.ndarray
    pose_ids: np.ndarray
    tree_file_ids: np.ndarray
    path: Path


@dataclass(frozen=True)
class AgentPair:
    """Two agents' maps with ground truth, shaped like ``simulate.Scenario``.

    ``p``/``q`` are the maps in each agent's first-pose frame, ``ids_p``/
    ``ids_q`` tree ids, ``truth`` the reference trees in p's frame (indexed
    by id), ``theta``/``t`` the true transform ``q ≈ R(θ) p + t``,
    ``sigma`` the RMS per-coordinate standard deviation of the map entries
    (from the agents' own covariances, no ground truth), ``cov_p``/``cov_q``
    per-tree covariances, ``poses_p``/``poses_q`` the agents' pose counts.

    Two truths: ``theta``/``t`` is the rigid fit between the two agents' maps
    over their common tree ids, the transform any matcher should find;
    ``theta_first_pose``/``t_first_pose`` relates the agents' first poses on
    the reference trajectory. They differ by the agents' own map errors.

    ``ids_p``/``ids_q`` name each landmark's physical tree (the smallest id
    of its group in ``physical_trees``), the ground truth of an association;
    ``log_ids_p``/``log_ids_q`` are the log's own tree ids (sorted, unique).
    """

    p: np.ndarray
    q: np.ndarray
    ids_p: np.ndarray
    ids_q: np.ndarray
    truth: np.ndarray
    sigma: float
    theta: float
    t: np.ndarray
    cov_p: np.ndarray
    cov_q: np.ndarray
    cut: int
    source: str
    poses_p: int
    poses_q: int
    theta_first_pose: float
    t_first_pose: np.ndarray
    log_ids_p: np.ndarray
    log_ids_q: np.ndarray

    @functools.cached_property
    def n_common(self) -> int:
        """Most correct pairs one-to-one: per physical tree in both maps, the fewer of its landmarks."""
        tree_p, count_p = np.unique(self.ids_p, return_counts=True)
        tree_q, count_q = np.unique(self.ids_q, return_counts=True)
        _, ip, iq = np.intersect1d(tree_p, tree_q, return_indices=True)
        return int(np.minimum(count_p[ip], count_q[iq]).sum())


def physical_trees(trees: np.ndarray, radius: float = SAME_TREE_RADIUS) -> np.ndarray:
    """The physical tree of each tree id: ids within ``radius`` of each other, transitively, are one.

    Returns
    -------
    (m,) int ndarray
        For id k, the smallest id of its group.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    close = cKDTree(trees).sparse_distance_matrix(cKDTree(trees), radius, output_type="coo_matrix")
    _, group = connected_components(close, directed=False)
    first = np.full(group.max() + 1, len(trees))
    np.minimum.at(first, group, np.arange(len(trees)))
    return first[group]


def _read_table(path: Path, columns: int) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"Victoria Park file not found: {path}")
    try:
        table = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"{path} is malformed: {exc}") from None
    if table.shape[1] != columns:
        raise DatasetError(f"{path} must have {columns} columns, got {table.shape[1]}")
    return table


def _read_log_records(log: Path):
    """The observation log's records: the pose chain's file ids, each odometry line's motion and
    covariance, and each tree observation (pose id, tree id, x, y) with its covariance."""
    pose_ids: list[int] = []
    odometry, odometry_cov, observations, obs_cov = [], [], [], []
    with open(log) as fh:
        for number, line in enumerate(fh, 1):
            fields = line.split()
            if not fields:
                continue
            try:
                if fields[0] == "ODOMETRY" and len(fields) == 12:
                    a, b = int(fields[1]), int(fields[2])
                    if not pose_ids:
                        pose_ids.append(a)
                    if a != pose_ids[-1]:
                        raise ValueError(f"odometry from pose {a} does not continue the chain at {pose_ids[-1]}")
                    pose_ids.append(b)
                    odometry.append([float(v) for v in fields[3:6]])
                    odometry_cov.append([float(v) for v in fields[6:12]])
                elif fields[0] == "LANDMARK" and len(fields) == 8:
                    observations.append((int(fields[1]), int(fields[2]), float(fields[3]), float(fields[4])))
                    cxx, cxy, cyy = (float(v) for v in fields[5:8])
                    obs_cov.append([[cxx, cxy], [cxy, cyy]])
                else:
                    raise ValueError(f"unknown record {fields[0]!r} with {len(fields)} fields")
            except ValueError as exc:
                raise DatasetError(f"{log}:{number}: {exc}") from None
    return pose_ids, odometry, odometry_cov, observations, obs_cov


def load_log(path=None) -> VictoriaParkLog:
    """Parse the Victoria Park files from ``path`` (default: the bundled copy).

    Raises
    ------
    DatasetError
        If a file is missing or a line does not parse.
    """
    root = Path(path) if path is not None else DATA_DIR
    log = root / LOG_FILE
    if not log.is_file():
        raise DatasetError(f"Victoria Park file not found: {log}")
    pose_ids, odometry, odometry_cov, observations, obs_cov = _read_log_records(log)
    index = {pid: i for i, pid in enumerate(pose_ids)}
    tree_ids: dict[int, int] = {}
    for _, lm, _, _ in observations:
        tree_ids.setdefault(lm, len(tree_ids))
    try:
        obs_pose = np.array([index[p] for p, _, _, _ in observations], dtype=np.intp)
    except KeyError as exc:
        raise DatasetError(f"{log}: observation from unknown pose {exc}") from None
    trajectory = _read_table(root / TRAJECTORY_FILE, 3)
    trees = _read_table(root / TREES_FILE, 2)
    if len(trees) != len(tree_ids):
        raise DatasetError(f"{root / TREES_FILE} has {len(trees)} trees, the log observes {len(tree_ids)}")
    return VictoriaParkLog(
        odometry=np.array(odometry),
        odometry_cov=np.array(odometry_cov),
        obs_pose=obs_pose,
        obs_tree=np.array([tree_ids[lm] for _, lm, _, _ in observations], dtype=np.intp),
        obs_xy=np.array([[x, y] for _, _, x, y in observations]),
        obs_cov=np.array(obs_cov).reshape(-1, 2, 2),
        trajectory=trajectory,
        trees=trees,
        pose_ids=np.array(pose_ids, dtype=np.int64),
        tree_file_ids=np.array(list(tree_ids), dtype=np.int64),
        path=log,
    )


def _to_frame(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points into the frame of ``pose`` = (x, y, θ): R(θ)ᵀ (w - t)."""
    return (points - pose[:2]) @ rotation(pose[2])


def _reference_map(log: VictoriaParkLog, sel: np.ndarray):
    """Trees of one agent from its observations placed with reference poses."""
    poses = log.trajectory[log.obs_pose[sel]]
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    xy = log.obs_xy[sel]
    world = poses[:, :2] + np.column_stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]])
    ids, inverse, counts = np.unique(log.obs_tree[sel], return_inverse=True, return_counts=True)
    mean = np.zeros((ids.size, 2))
    np.add.at(mean, inverse, world)
    mean /= counts[:, None]
    resid = world - mean[inverse]
    dof = 2 * (len(world) - ids.size)
    # Pooled variance of one observation per coordinate, from this agent's scatter.
    var_obs = float(np.sum(resid**2) / dof) if dof > 0 else float(np.mean(resid**2) + 1.0)
    cov = (var_obs / counts)[:, None, None] * np.eye(2)
    return ids, mean, cov


def victoria_park(cut: int = DEFAULT_CUT, source: str = "reference", path=None, min_sightings: int = 1) -> AgentPair:
    """Two agents' tree maps of Victoria Park, split at pose index ``cut``.

    Parameters
    ----------
    cut : int, default 3483
        Agent p drives poses ``0 .. cut-1``, agent q ``cut ..`` the end
        (pose indices counted along the odometry chain).
    source : {"reference", "slam"}
        How each agent builds its map (see the module docstring).
    path : path, optional
        Folder holding the three data files; default the bundled copy.
    min_sightings : int, default 1
        Each agent publishes only the trees it sighted at least this often
        itself (landmark confirmation, as SLAM front ends do against
        spurious detections; the SLAM solve still uses every sighting).
        The default keeps every tree.

    Returns
    -------
    AgentPair

    Raises
    ------
    ValueError
        On a bad ``cut``, ``source`` or ``min_sightings``; ``DatasetError``
        on bad files.
    """
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    log = load_log(path)
    n_ref = log.trajectory.shape[0]
    cut = _check_cut(cut, min_sightings, n_ref)
    # Observations from poses without a reference pose cannot be placed (the SLAM solve uses them).
    valid = log.obs_pose < n_ref if source == "reference" else np.ones(len(log.obs_pose), bool)
    sel_p, sel_q = valid & (log.obs_pose < cut), valid & (log.obs_pose >= cut)
    first_p, first_q = log.trajectory[0], log.trajectory[cut]
    (ids_p, p, cov_p), (ids_q, q, cov_q) = _agent_tree_maps(log, source, (sel_p, sel_q), cut, path)
    seen_p = np.bincount(log.obs_tree[sel_p], minlength=len(log.trees))[ids_p] >= min_sightings
    seen_q = np.bincount(log.obs_tree[sel_q], minlength=len(log.trees))[ids_q] >= min_sightings
    ids_p, p, cov_p = ids_p[seen_p], p[seen_p], cov_p[seen_p]
    ids_q, q, cov_q = ids_q[seen_q], q[seen_q], cov_q[seen_q]
    if len(ids_p) < 3 or len(ids_q) < 3:
        raise ValueError(f"cut={cut} (min_sightings={min_sightings}) leaves an agent with fewer than 3 trees")
    theta_first = float(wrap_angle(first_p[2] - first_q[2]))
    t_first = (first_p[:2] - first_q[:2]) @ rotation(first_q[2])
    _, ip, iq = np.intersect1d(ids_p, ids_q, return_indices=True)
    fit = align_pairs(p[ip], q[iq], 1.0) if ip.size >= 2 else None
    physical = physical_trees(log.trees)
    sigma = pooled_sigma(cov_p, cov_q)
    pair = AgentPair(
        p=p, q=q, ids_p=physical[ids_p], ids_q=physical[ids_q], log_ids_p=ids_p, log_ids_q=ids_q,
        truth=_to_frame(log.trees, first_p),
        sigma=sigma, theta=theta_first if fit is None else fit.theta, t=t_first if fit is None else fit.t,
        cov_p=cov_p, cov_q=cov_q, cut=cut, source=source, poses_p=cut, poses_q=n_ref - cut,
        theta_first_pose=theta_first, t_first_pose=t_first,
    )
    _warn_of_bad_maps(pair)
    return pair


def _check_cut(cut, min_sightings, n_ref: int) -> int:
    """``cut`` as an int, after a ValueError on a bad ``cut`` (``n_ref`` reference poses) or ``min_sightings``."""
    if isinstance(cut, bool) or int(cut) != cut or not 1 <= cut < n_ref - 1:
        raise ValueError(f"cut must be an integer pose index in [1, {n_ref - 2}], got {cut!r}")
    if isinstance(min_sightings, bool) or int(min_sightings) != min_sightings or min_sightings < 1:
        raise ValueError(f"min_sightings must be an integer >= 1, got {min_sightings!r}")
    return int(cut)


def _agent_tree_maps(log: VictoriaParkLog, source: str, selections: tuple, cut: int, path):
    """Each agent's (ids, trees in its first pose's frame, covariances), built as ``source`` says from its
    observations ``selections`` (p's, q's)."""
    if source == "slam":
        return slam_map(0, cut, path), slam_map(cut, None, path)
    maps = []
    for sel, first in zip(selections, (log.trajectory[0], log.trajectory[cut])):
        ids, world, cov = _reference_map(log, sel)
        rot = rotation(first[2])
        maps.append((ids, _to_frame(world, first), rot.T @ cov @ rot))
    return maps


def _warn_of_bad_maps(pair: AgentPair) -> None:
    """Warn of an agent's map further from the reference map than its own covariances allow."""
    for agent, quality in map_quality(pair).items():
        expected = np.sqrt(2) * quality["rms_sd"]  # RMS distance its own covariances predict
        if quality["rmse"] > QUALITY_WARNING * expected:
            warnings.warn(f"Victoria Park cut {pair.cut} ({pair.source}): agent {agent}'s map is "
                          f"{quality['rmse']:.1f} m RMS from the reference map after a rigid fit, "
                          f"{quality['rmse'] / expected:.1f} times what its own covariances predict", stacklevel=3)


#: Per-tree covariances ``slam_map`` can report (see there).
GAUGES = ("shape", "first_pose")


def slam_map(start: int = 0, stop: int | None = None, path=None, gauge: str = "shape", solver=None):
    """One agent's own SLAM map of poses ``start .. stop-1`` (all by default), solved with GTSAM's iSAM2.

    The solver of ``victoria_park(..., source="slam")`` (optional extra
    ``[slam]``), cached on disk. Solving the whole drive checks the solver
    against the reference map: what an agent's map lacks then is data
    (the loop closures it never drove), not optimisation.

    Parameters
    ----------
    gauge : {"shape", "first_pose"}
        Which per-tree covariance to report. ``"first_pose"``: the marginal
        covariance with the agent's first pose held fixed; it grows with
        the distance driven, mostly from heading error that turns the whole
        map. ``"shape"`` (default): the same joint covariance with the
        map's rigid motion removed (``rigid_free_covariance``). Merging
        estimates that rigid motion, so only the shape error is left to
        gate associations and weight the fusion.
    solver : dict, optional
        Solver settings other than the defaults, for checking that a map's
        error is the data's and not the solver's: ``relinearize_threshold``
        (default 0.1), ``relinearize_skip`` (10; 1 relinearises at every
        pose), ``batch_refinement`` (True), ``sighting_noise`` (``"file"``:
        each sighting's covariance from the data file; ``"load2d"``: GTSAM
        ``load2D``'s bearing noise of 0.2 rad at any range),
        ``sighting_kernel`` (None, or ``"huber"`` for a Huber M-estimator on
        the tree sightings) and ``prior_sigma`` (1e-6, the first pose's
        anchor).

    Returns
    -------
    ids : (m,) int ndarray
        Rows of the reference tree map (``load_log(path).trees``).
    points : (m, 2) ndarray
        The trees in the frame of pose ``start``.
    cov : (m, 2, 2) ndarray
        Their covariances in the chosen gauge.
    """
    from ._slam import agent_map

    if gauge not in GAUGES:
        raise ValueError(f"gauge must be one of {GAUGES}, got {gauge!r}")
    log = load_log(path)
    stop = len(log.pose_ids) if stop is None else stop
    if not 0 <= start < stop <= len(log.pose_ids):
        raise ValueError(f"need 0 <= start < stop <= {len(log.pose_ids)}, got start={start}, stop={stop}")
    if not np.any((log.obs_pose >= start) & (log.obs_pose < stop)):
        raise ValueError(f"poses {start}..{stop - 1} sight no tree: choose a longer range of poses")
    ids, points, joint = agent_map(log, start, stop, settings=solver)
    if gauge == "shape":
        joint = rigid_free_covariance(points, joint)
    m = len(ids)
    return ids, points, joint.reshape(m, 2, m, 2)[np.arange(m), :, np.arange(m), :]


def rigid_free_covariance(points: np.ndarray, joint: np.ndarray) -> np.ndarray:
    """A map's joint covariance with its rigid motion removed (an S-transformation).

    An error that turns and shifts the whole map is invisible once the map
    is aligned to another: this is the covariance of the residual left
    after a least-squares rigid fit over all of the map's points,
    ``A Σ Aᵀ`` with ``A = I - J J⁺`` (``J⁺`` the pseudo-inverse, which is
    ``(JᵀJ)⁻¹ Jᵀ`` for two or more distinct points) and ``J`` the points'
    motion under a small rotation about their centroid and a translation.

    Parameters
    ----------
    points : (m, 2) ndarray
    joint : (2m, 2m) ndarray
        Covariance of (x_0, y_0, x_1, y_1, ...).

    Returns
    -------
    (2m, 2m) ndarray
    """
    m = len(points)
    centred = points - points.mean(axis=0)
    J = np.zeros((2 * m, 3))
    J[0::2, 0], J[1::2, 0] = -centred[:, 1], centred[:, 0]
    J[0::2, 1] = J[1::2, 2] = 1.0
    A = np.eye(2 * m) - J @ np.linalg.pinv(J)  # pinv: one tree alone moves rigidly in every direction
    return A @ joint @ A.T


#: ``victoria_park`` warns when an agent's map error (RMS distance from the
#: reference map after a rigid fit) exceeds this many times the RMS distance
#: its own covariances predict.
QUALITY_WARNING = 2.0


def fit_error(points: np.ndarray, reference: np.ndarray) -> dict:
    """Rigid fit (closed form) of ``points`` onto ``reference``, row k to row k.

    Returns ``rmse`` and ``max`` of the residual distances and the fitted
    rotation ``rot_deg``.
    """
    al = align_pairs(points, reference, 1.0)
    dist = np.sqrt(np.sum((rotate(al.theta, points) + al.t - reference) ** 2, axis=1))
    return {"rmse": float(np.sqrt(np.mean(dist**2))), "max": float(dist.max()), "rot_deg": float(np.degrees(al.theta))}


def map_quality(pair: AgentPair) -> dict:
    """How right each agent's own map is: rigid fit onto the reference tree map by tree id.

    Returns
    -------
    dict
        ``{"p": {...}, "q": {...}}``, each with ``rmse`` and ``max`` (metres,
        after the fit), ``rot_deg`` (the fit's rotation), ``rms_sd`` (the
        RMS per-coordinate standard deviation the agent reports for
        its trees) and ``trees``.
    """
    out = {}
    for agent, pts, ids, cov in (("p", pair.p, pair.log_ids_p, pair.cov_p), ("q", pair.q, pair.log_ids_q, pair.cov_q)):
        out[agent] = {**fit_error(pts, pair.truth[ids]), "trees": int(len(ids)),
                      "rms_sd": float(np.sqrt(np.mean(np.trace(cov, axis1=1, axis2=2) / 2)))}
    return out


# MR.CLAM: the files and each robot's map (the solver is ``mapmerge.mrclam``).

#: Where the bundled copy of MR.CLAM dataset 7 lives.
MRCLAM_DIR = Path(__file__).resolve().parent / "data" / "mrclam"


def _mrclam_file(root: Path, name: str) -> Path:
    for candidate in (root / name, root / f"{name}.gz"):
        if candidate.is_file():
            return candidate
    raise DatasetError(f"MR.CLAM file not found: {root / name} (or {name}.gz)")


def _mrclam_table(root: Path, name: str, columns: int) -> np.ndarray:
    path = _mrclam_file(root, name)
    try:
        table = np.loadtxt(path, ndmin=2, comments="#")
    except (ValueError, OSError) as exc:
        raise DatasetError(f"{path} is malformed: {exc}") from None
    if table.shape[1] != columns or len(table) == 0:
        raise DatasetError(f"{path} must have {columns} columns and at least one line, got shape {table.shape}")
    return table


def _mrclam_first_time(root: Path, name: str) -> float:
    path = _mrclam_file(root, name)
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as fh:
        for line in fh:
            if line.strip() and not line.lstrip().startswith("#"):
                try:
                    return float(line.split()[0])
                except ValueError:
                    break
    raise DatasetError(f"{path} has no data line")


def load_mrclam(path=None, robots=mrclam_slam.ROBOTS) -> mrclam_slam.Recording:
    """Parse an MR.CLAM dataset directory (default: the bundled copy of dataset 7).

    Each file may be the original ``X.dat`` or gzip-compressed ``X.dat.gz``.

    Raises
    ------
    DatasetError
        If the directory or a file is missing or a file does not parse.
    """
    root = Path(path) if path is not None else MRCLAM_DIR
    if not root.is_dir():
        raise DatasetError(f"MR.CLAM directory not found: {root}")
    barcodes = _mrclam_table(root, "Barcodes.dat", 2).astype(np.int64)
    landmarks = _mrclam_table(root, "Landmark_Groundtruth.dat", 5)[:, :3]
    subject_of = dict(zip(barcodes[:, 1].tolist(), barcodes[:, 0].tolist()))
    start = min(_mrclam_first_time(root, f"Robot{k}_Groundtruth.dat") for k in mrclam_slam.ROBOTS)
    logs = {}
    for k in robots:
        odometry = _mrclam_table(root, f"Robot{k}_Odometry.dat", 3)
        odometry = odometry[np.r_[np.diff(odometry[:, 0]) > 0, True]]
        if np.any(np.diff(odometry[:, 0]) < 0):
            raise DatasetError(f"Robot{k}_Odometry.dat: time stamps go backwards")
        raw = _mrclam_table(root, f"Robot{k}_Measurement.dat", 4)
        subject = np.array([subject_of.get(int(b), -1) for b in raw[:, 1]])
        seen = np.column_stack([raw[:, 0], subject, raw[:, 2:]])
        is_landmark = np.isin(subject, landmarks[:, 0])
        logs[k] = mrclam_slam.RobotLog(
            robot=k, odometry=odometry, sightings=seen[is_landmark],
            robot_sightings=seen[(subject >= 1) & (subject <= len(mrclam_slam.ROBOTS))], misread=int(np.sum(subject < 0)),
            groundtruth=_mrclam_table(root, f"Robot{k}_Groundtruth.dat", 4),
        )
    return mrclam_slam.Recording(landmarks=landmarks, start=start, robots=logs, path=root)


def _check_mrclam_robots(robots) -> tuple:
    try:
        chosen = tuple(robots)
    except TypeError:
        chosen = None
    ok = (chosen is not None and len(chosen) > 0 and len(set(chosen)) == len(chosen)
          and all(not isinstance(k, bool) and isinstance(k, (int, np.integer)) and k in mrclam_slam.ROBOTS for k in chosen))
    if not ok:
        raise ValueError(f"robots must be distinct robot numbers among {mrclam_slam.ROBOTS}, got {robots!r}")
    return tuple(int(k) for k in chosen)


def _check_until_s(until_s):
    if until_s is None:
        return None
    if isinstance(until_s, bool) or not isinstance(until_s, (int, float, np.integer, np.floating)) \
            or not 0 < until_s < np.inf:
        raise ValueError(f"until_s must be a positive number of seconds or None, got {until_s!r}")
    return float(until_s)


def mrclam(path=None, robots=(1, 2, 3, 4, 5), until_s=None) -> mrclam_slam.MrclamTeam:
    """Each robot's own landmark map of MR.CLAM dataset 7 (five robots, 15 landmarks), solved with iSAM2.

    ``mapmerge.mrclam`` documents the method: per robot, a calibration of
    its odometry delay and noise, its sighting noise and its systematic
    landmark error against the Vicon poses, then iSAM2 over its own
    odometry and landmark sightings (robust Huber bearing-range factors), a
    batch refinement, one rejection of gross misreads, and the landmarks'
    marginal covariances plus the systematic error; each map in the frame of
    the robot's first pose.
    Needs GTSAM (optional extra ``[slam]``); solves are cached on disk.

    Parameters
    ----------
    path : path, optional
        An MR.CLAM dataset directory in the original file format
        (``Barcodes.dat``, ``Landmark_Groundtruth.dat``, ``RobotK_Odometry.dat``,
        ``RobotK_Measurement.dat``, ``RobotK_Groundtruth.dat``; each may be
        gzip-compressed as ``.dat.gz``). Default: the bundled copy of dataset 7.
    robots : sequence of int, default (1, 2, 3, 4, 5)
        Which robots, in the order of the returned lists.
    until_s : float, optional
        Use only data up to this many seconds after the start of the
        recording (the first Vicon time stamp); default the whole logs. The
        calibration always uses the whole logs.

    Returns
    -------
    mapmerge.mrclam.MrclamTeam
        ``maps``, ``covs``, ``ids`` per robot, ``truth`` (surveyed landmarks
        by subject number), ``first_poses``, ``theta``/``t`` (fit of each map
        onto the surveyed landmarks: map_i ≈ R(θ_i) world + t_i), ``sigma``,
        ``stranger``, ``rms`` (each map's error after that fit) and the
        calibrations.

    Raises
    ------
    ValueError
        On bad ``robots`` or ``until_s`` (or an ``until_s`` before a robot
        sighted two landmarks); ``DatasetError`` on a missing or malformed
        directory or file.
    """
    robots = _check_mrclam_robots(robots)
    until_s = _check_until_s(until_s)
    recording = load_mrclam(path, robots)
    memory = mrclam_slam.memory()
    solvers = memory.cache(mrclam_slam.calibrate), memory.cache(mrclam_slam.solve_robot)
    truth = np.full((max(mrclam_slam.LANDMARKS) + 1, 2), np.nan)
    truth[recording.landmarks[:, 0].astype(int)] = recording.landmarks[:, 1:]
    rows = [_mrclam_robot(recording, k, until_s, solvers, truth) for k in robots]
    return _mrclam_team(robots, rows, truth, until_s)


def _mrclam_robot(recording: mrclam_slam.Recording, k: int, until_s, solvers: tuple, truth: np.ndarray) -> dict:
    """Robot k's calibration, map and its fit onto the surveyed landmarks ``truth``, with the cached
    ``solvers`` (calibrate, solve_robot); ``until_s`` as for ``mrclam``."""
    cached_calibrate, cached_solve = solvers
    log = recording.robots[k]
    cal = cached_calibrate(log, recording.landmarks, mrclam_slam.CALIBRATION_WINDOW, mrclam_slam.DELAY_GRID)
    first = log.odometry[0, 0]
    end = log.odometry[-1, 0] if until_s is None else min(log.odometry[-1, 0], recording.start + until_s)
    use = (log.sightings[:, 0] >= first) & (log.sightings[:, 0] <= end)
    if end <= first or np.unique(log.sightings[use, 1]).size < 2:
        raise ValueError(f"until_s={until_s} leaves robot {k} with fewer than 2 landmarks sighted: "
                         "choose a longer time")
    sol = cached_solve(log.odometry[log.odometry[:, 0] <= end], log.sightings[use], float(end), cal.delay,
                       cal.odometry_sigma, np.array([cal.bearing_sigma, cal.range_sigma]), mrclam_slam.solver_settings())
    ids, points, joint = sol["ids"], sol["points"], sol["joint"]
    m = len(ids)
    floor = cal.landmark_sigma**2 * np.eye(2)
    covs = joint.reshape(m, 2, m, 2)[np.arange(m), :, np.arange(m), :] + floor
    shape = rigid_free_covariance(points, joint).reshape(m, 2, m, 2)[np.arange(m), :, np.arange(m), :] + floor
    fit = align_pairs(truth[ids], points, 1.0)  # map ≈ R(θ) world + t
    return {"maps": points, "covs": covs, "shape_covs": shape, "ids": ids,
            "first_poses": mrclam_slam.vicon_poses(log.groundtruth, np.array([first]))[0],
            "theta": fit.theta, "t": fit.t, "sigma": float(np.sqrt(np.mean(np.trace(shape, axis1=1, axis2=2) / 2))),
            "rms": fit_error(points, truth[ids])["rmse"],
            "rms_incremental": fit_error(sol["incremental"], truth[ids])["rmse"],
            "sightings": int(use.sum()), "rejected": sol["rejected"], "calibrations": cal}


def _mrclam_team(robots: tuple, rows: list, truth: np.ndarray, until_s) -> mrclam_slam.MrclamTeam:
    """The robots' ``_mrclam_robot`` rows as one team."""
    out = {name: [row[name] for row in rows] for name in rows[0]}
    first_poses = np.array(out["first_poses"])
    first_poses[:, 2] = wrap_angle(first_poses[:, 2])
    return mrclam_slam.MrclamTeam(
        robots=robots, maps=out["maps"], covs=out["covs"], shape_covs=out["shape_covs"], ids=out["ids"],
        truth=truth, first_poses=first_poses, theta=wrap_angle(np.array(out["theta"])), t=np.array(out["t"]),
        sigma=np.array(out["sigma"]), stranger=np.zeros(len(robots), bool), rms=np.array(out["rms"]),
        rms_incremental=np.array(out["rms_incremental"]), sightings=np.array(out["sightings"]),
        rejected=np.array(out["rejected"]),
        calibrations=tuple(out["calibrations"]), until_s=until_s,
    )
