"""Real multi-robot data: five MR.CLAM robots' own maps merged into one (results/mrclam/).

    python -m experiments.mrclam [--out results/mrclam] [--path DIR]

Each robot builds its own landmark map (``mapmerge.datasets.mrclam``: iSAM2
over its own odometry and landmark sightings, noise models calibrated
against Vicon) from the first ``until_s`` seconds of the recording
(``UNTILS``: 120, 300, 600 and 900 s, and the whole logs; the recording
lasts 900.0 s, so 900 s is the whole logs but for the last few milliseconds). Writes:

- ``calibration.csv/.md``: each robot's calibration (whole logs).
- ``robots.csv/.md``: per ``until_s`` and robot, landmarks seen, sightings,
  the map's RMS distance from the surveyed landmarks after a rigid fit by
  ids (``rms``; also for the iSAM2 estimate before the batch refinement)
  and the RMS standard deviation its covariances claim.
- ``pairs.csv/.md``: every pair of robots merged with ``merge_maps``
  (``PAIR_METHODS``, each map's rigid-free covariances): matched, common
  landmarks, correct / wrong landmark pairs (by ids), rotation and
  translation error against the fits by ids.
- ``group.csv/.md``: ``merge_many`` of the five maps (its default method), placement ``joint``
  and the baselines ``tree`` and ``chain``, with each map's rigid-free
  covariances (``shape``) and, for comparison, the covariances with the
  first pose held fixed (``first_pose``), scored by
  ``metrics.group_errors`` (the fit by ids as the truth of each frame);
  ``fused_fit_rms`` is the fused map's RMS distance from the surveyed
  landmarks after its own rigid fit by ids (pure tracks), comparable with
  the robots' ``rms``.
- ``mrclam.png/.pdf``: the five maps placed by ``merge_many`` and the fused
  map over the surveyed landmarks, at 120 s and on the whole logs.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from mapmerge.alignment import rotate, wrap_angle
from mapmerge.datasets import fit_error, mrclam
from mapmerge.group import merge_many
from mapmerge.merging import merge_maps
from mapmerge.metrics import group_errors

from .aggregate import save_table
from .figures import STYLE

#: Seconds of the recording each robot's map is built from (None: the whole logs, 900.0 s).
UNTILS = (120, 300, 600, 900, None)
PLACEMENTS = ("joint", "tree", "chain")
GAUGES = {"shape": "shape_covs", "first_pose": "covs"}
#: The methods of the pairwise table: consensus, and consensus_count, whose test is meant for maps this small.
PAIR_METHODS = ("consensus", "consensus_count")
SEED = 0
COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def label(until_s) -> str:
    return "all" if until_s is None else f"{until_s:g}"


def robot_rows(team) -> list[dict]:
    return [{"until_s": label(team.until_s), "robot": k, "landmarks": len(team.ids[i]),
             "sightings": int(team.sightings[i]), "rms": team.rms[i], "rms_isam2": team.rms_incremental[i],
             "rms_per_coord": team.rms[i] / np.sqrt(2), "sigma": team.sigma[i]}
            for i, k in enumerate(team.robots)]


def calibration_rows(team) -> list[dict]:
    return [{"robot": k, "delay_s": c.delay, "odo_forward": c.odometry_sigma[0], "odo_lateral": c.odometry_sigma[1],
             "odo_heading": c.odometry_sigma[2], "heading_undelayed": c.heading_rms_undelayed,
             "range_sigma": c.range_sigma, "bearing_sigma": c.bearing_sigma, "range_bias": c.range_bias,
             "bearing_bias": c.bearing_bias, "landmark_sigma": c.landmark_sigma, "windows": c.windows,
             "sightings": c.sightings}
            for k, c in zip(team.robots, team.calibrations)]


def true_pair(team, i, j):
    """map_j ≈ R(θ) map_i + t from the two fits by ids (map_k ≈ R(θ_k) world + t_k)."""
    theta = float(wrap_angle(team.theta[j] - team.theta[i]))
    return theta, team.t[j] - rotate(theta, team.t[i][None])[0]


def pair_rows(team) -> list[dict]:
    rows = []
    for method, (i, j) in itertools.product(PAIR_METHODS, itertools.combinations(range(len(team.maps)), 2)):
        start = time.perf_counter()
        res = merge_maps(team.maps[i], team.maps[j], method=method, cov_p=team.shape_covs[i],
                         cov_q=team.shape_covs[j], rng=SEED)
        ms = 1e3 * (time.perf_counter() - start)
        theta, t = true_pair(team, i, j)
        right = team.ids[i][res.pairs[:, 0]] == team.ids[j][res.pairs[:, 1]] if len(res.pairs) else np.zeros(0, bool)
        rows.append({
            "until_s": label(team.until_s), "method": method, "robots": f"{team.robots[i]}-{team.robots[j]}",
            "common": len(np.intersect1d(team.ids[i], team.ids[j])), "matched": bool(res.matched),
            "correct_pairs": int(right.sum()), "wrong_pairs": int((~right).sum()),
            "rot_err_deg": float(np.degrees(abs(wrap_angle(res.theta - theta)))) if res.matched else np.nan,
            "trans_err": float(np.hypot(*(res.t - t))) if res.matched else np.nan, "ms": ms,
        })
    return rows


def fused_fit_rms(team, g) -> float:
    """RMS distance (m) of the fused map's pure tracks from the surveyed landmarks after a rigid fit by ids."""
    ids = np.full(g.tracks.shape, -1)
    for i in range(len(team.maps)):
        rows = g.tracks[:, i]
        ids[rows >= 0, i] = team.ids[i][rows[rows >= 0]]
    first = ids.max(axis=1)
    pure = np.all((ids == first[:, None]) | (ids < 0), axis=1) & (first >= 0)
    return fit_error(g.merged[pure], team.truth[first[pure]])["rmse"] if pure.sum() >= 3 else np.nan


def group_rows(team, merges: dict) -> list[dict]:
    rows = []
    best = int(np.argmin(team.rms))
    for gauge, attr in GAUGES.items():
        for placement in PLACEMENTS:
            start = time.perf_counter()
            g = merge_many(team.maps, covs=getattr(team, attr), placement=placement, rng=SEED)
            seconds = time.perf_counter() - start
            merges[(label(team.until_s), gauge, placement)] = g
            err = group_errors(team, g)
            statuses = [e.status for e in g.edges]
            rows.append({
                "until_s": label(team.until_s), "covariances": gauge, "placement": placement,
                "placed_correct": err["placed_correct"], "placed_wrong": err["placed_wrong"],
                "unplaced": err["unplaced"], "max_rot_err_deg": np.nanmax(err["rot_err_deg"]),
                "edges_accepted": statuses.count("accepted"), "edges_inconsistent": statuses.count("inconsistent"),
                "edges_no_match": statuses.count("no match"), "tracks": len(g.merged),
                "track_purity": err["track_purity"], "track_completeness": err["track_completeness"],
                "duplicates": err["duplicates"], "fused_rmse": err["fused_rmse"], "shared_rmse": err["shared_rmse"],
                "best_robot_rms_per_coord": team.rms[best] / np.sqrt(2), "fused_fit_rms": fused_fit_rms(team, g),
                "best_robot_rms": team.rms[best], "best_robot": team.robots[best], "s": seconds,
            })
    return rows


def to_world(team, g, x_ref):
    """Points of the reference frame into the surveyed (world) frame by the reference map's fit by ids."""
    r = g.reference
    return rotate(-team.theta[r], x_ref - team.t[r])


def figure(teams: dict, merges: dict, out: Path) -> list[Path]:
    shown = [u for u in (120, None) if label(u) in teams]
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(1, len(shown), figsize=(2.6 * len(shown) + 1.4, 4.2), squeeze=False)
        for ax, until_s in zip(axes[0], shown):
            team, g = teams[label(until_s)], merges[(label(until_s), "shape", "joint")]
            surveyed = team.truth[~np.isnan(team.truth[:, 0])]
            ax.scatter(*surveyed.T, marker="s", s=22, facecolors="none", edgecolors="0.3", lw=0.8,
                       label="surveyed landmarks", zorder=1)
            for i, k in enumerate(team.robots):
                if not g.placed[i]:
                    continue
                in_ref = rotate(-g.theta[i], team.maps[i] - g.t[i])  # map i ≈ R(θ_i) x_ref + t_i
                ax.scatter(*to_world(team, g, in_ref).T, s=6, color=COLORS[i % len(COLORS)],
                           label=f"robot {k}", zorder=2)
            ax.scatter(*to_world(team, g, g.merged).T, marker="+", s=30, color="k", lw=0.8,
                       label="fused", zorder=3)
            placed = int(g.placed.sum())
            ax.set_title(f"{'whole logs' if until_s is None else f'first {until_s} s'}: "
                         f"{placed} of {len(team.robots)} robots placed")
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
        axes[0, -1].legend(loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)
        fig.tight_layout()
        paths = [out / "mrclam.png", out / "mrclam.pdf"]
        fig.savefig(paths[0], metadata={"Software": None})
        fig.savefig(paths[1], metadata={"CreationDate": None, "Creator": None, "Producer": None})
        plt.close(fig)
    return paths


def run(out: Path, path=None) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    teams, merges = {}, {}
    robots, pairs, group = [], [], []
    for until_s in UNTILS:
        team = mrclam(path, until_s=until_s)
        teams[label(until_s)] = team
        robots += robot_rows(team)
        pairs += pair_rows(team)
        group += group_rows(team, merges)
    written = save_table(pd.DataFrame(calibration_rows(teams["all"])), out / "calibration")
    written += save_table(pd.DataFrame(robots), out / "robots")
    written += save_table(pd.DataFrame(pairs).drop(columns="ms"), out / "pairs")
    written += save_table(pd.DataFrame(group).drop(columns="s"), out / "group")
    timing = pd.DataFrame(group)[["until_s", "covariances", "placement", "s"]]
    written += save_table(timing, out / "timing")
    written += figure(teams, merges, out)
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Merge the five MR.CLAM robots' own maps.")
    parser.add_argument("--out", type=Path, default=Path("results/mrclam"))
    parser.add_argument("--path", type=Path, default=None,
                        help="an MR.CLAM dataset directory in the original format (default: the bundled dataset 7)")
    args = parser.parse_args(argv)
    for path in run(args.out, args.path):
        print(path)


if __name__ == "__main__":
    main()
