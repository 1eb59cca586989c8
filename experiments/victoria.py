"""Real data: every matcher on two agents' maps of Victoria Park (results/victoria_park/).

    python -m experiments.victoria            # run the preset, then table and figure
    python -m experiments.victoria --tables   # only rebuild them from the last run

Runs ``experiment=victoria_park`` (6 cut points x 2 map sources x 6 methods;
the ``slam`` source is skipped when GTSAM is not installed, ``astroalign``
when astroalign is not) and writes ``table.csv`` / ``table.md``: trees per
agent, common trees, correspondences found (correct / wrong), rotation and
translation error, combined-map RMSE against the reference tree map, and
time per merge; ``victoria_park.png`` / ``.pdf``: both agents' maps, the
merged map and the reference trees at the default cut; and, with the slam
source, ``solver_check.md``: the same SLAM solver on the whole drive against
the reference tree map; and ``min_sightings.md``: the default method
(``consensus_count``: ``consensus`` on maps of more than 50 trees) on the
SLAM maps when each agent publishes only the trees it sighted at least
1, 2 or 3 times; and ``rigidity.md``: per cut and source, the default method
followed by ``residual_match`` on the trees it left unpaired (a second
significant rigid match: one agent's map is bent).
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from scipy.spatial import ConvexHull  # noqa: E402

from mapmerge.alignment import align_pairs, rotate, wrap_angle  # noqa: E402
from mapmerge.datasets import DEFAULT_CUT, fit_error, load_log, map_quality, slam_map, victoria_park  # noqa: E402
from mapmerge.merging import merge_maps, residual_match  # noqa: E402
from mapmerge.metrics import map_errors, oracle_association, transform_oracle_association  # noqa: E402

from .aggregate import find_runs, save_table  # noqa: E402
from .figures import STYLE, save_figure  # noqa: E402
from .paper import run_module  # noqa: E402

SWEEP = Path("outputs/sweeps/victoria_park")
#: A tree the whole log sighted at most this many times has a reference
#: position from one or two laser returns, and the log's own association may
#: have split it from a nearby tree's track (48 of the 151 ids): wrong pairs
#: involving such a tree are counted apart, as their ground truth is weak.
FEW_SIGHTINGS = 2
#: The two consensus methods (the default, ``consensus_count``, differs on maps of at most 50 trees): run
#: with and without the agents' covariances.
CONSENSUS_METHODS = ("consensus", "consensus_count")
COLUMNS = {
    "cut": "cut", "source": "source", "method": "method", "use_cov": "covariances", "n_p": "trees p",
    "n_q": "trees q", "n_common_landmarks": "common", "map_rmse_p": "map RMSE p (m)", "map_rmse_q": "map RMSE q (m)",
    "correct_pairs": "correct", "wrong_pairs": "wrong", "wrong_few": f"of them on a tree seen <= {FEW_SIGHTINGS}x",
    "oracle_correct": "oracle correct", "oracle_wrong": "oracle wrong",
    "oracle_wrong_few": f"of them on a tree seen <= {FEW_SIGHTINGS}x (oracle)",
    "transform_oracle_correct": "transform oracle correct", "transform_oracle_wrong": "transform oracle wrong",
    "rot_err_deg": "rot err (deg)",
    "rot_err_first_pose_deg": "rot err vs first poses (deg)",
    "rot_err_own_deg": "rot err vs its correct pairs' fit (deg)", "fused_rmse": "fused RMSE (m)",
    "agents_rmse": "better agent, same trees (m)", "ms": "time (ms)",
}


def load_runs(sweep: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    trials, examples = [], []
    for run in find_runs([sweep]):
        t = pd.read_parquet(run / "trials.parquet")
        t = t.merge(pd.read_parquet(run / "timings.parquet"), on=["trial", "tau"])
        trials.append(t)
        if (run / "example_landmarks.parquet").exists():
            cell = t[["cut", "source", "method", "use_cov"]].iloc[0].to_dict()
            examples.append(pd.read_parquet(run / "example_landmarks.parquet").assign(**cell))
    return pd.concat(trials, ignore_index=True), pd.concat(examples, ignore_index=True)


def quality(cut: int, source: str) -> tuple[dict, object]:
    """Each agent's map against the reference map (rigid fit by tree id), and the data."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the table reports the errors the warning is about
        pair = victoria_park(cut=cut, source=source)
    return map_quality(pair), pair


@functools.cache
def tree_sightings() -> np.ndarray:
    """How often the whole log sighted each tree id."""
    log = load_log()
    return np.bincount(log.obs_tree, minlength=len(log.trees))


def wrong_on_few_sightings(pair, rows_p, rows_q) -> int:
    """How many wrong pairs (rows of p, rows of q) involve a tree seen at most ``FEW_SIGHTINGS`` times."""
    seen = tree_sightings()
    wrong = pair.ids_p[rows_p] != pair.ids_q[rows_q]
    few = np.minimum(seen[pair.log_ids_p[rows_p]], seen[pair.log_ids_q[rows_q]]) <= FEW_SIGHTINGS
    return int(np.sum(wrong & few))


def oracle_pairs(pair) -> tuple[int, int, int, int, int]:
    """Correct and wrong pairs of the oracle association (the fit-by-ids transform, the agents'
    covariances, q's density over its hull, π = 1/2), the wrong ones on rarely seen trees, and the
    correct and wrong pairs of the transform oracle (``consensus``'s own association at that transform,
    with the agents' covariances)."""
    density = len(pair.q) / ConvexHull(pair.q).volume
    pairs = oracle_association(pair.p, pair.q, pair.theta, pair.t, pair.cov_p, pair.cov_q, density, 0.5)
    correct = int(np.sum(pair.ids_p[pairs[:, 0]] == pair.ids_q[pairs[:, 1]]))
    known = transform_oracle_association(pair.p, pair.q, pair.theta, pair.t, pair.sigma, pair.cov_p, pair.cov_q)
    known_correct = int(np.sum(pair.ids_p[known[:, 0]] == pair.ids_q[known[:, 1]]))
    return (correct, len(pairs) - correct, wrong_on_few_sightings(pair, pairs[:, 0], pairs[:, 1]), known_correct,
            len(known) - known_correct)


def _fused_rows(merged: pd.DataFrame):
    """The merged map's fused rows and the rows of p and q each one fuses."""
    fused = merged[merged.origin == "fused"]
    return fused, fused.index_p.to_numpy(), fused.index_q.to_numpy()


def fused_vs_agents(merged: pd.DataFrame, pair) -> tuple[float, float]:
    """RMSE (after a rigid fit onto the reference trees) of the fused rows, and the better of the
    two agents' own maps over the same landmarks (each against its own tree)."""
    fused, rows_p, rows_q = _fused_rows(merged)
    if len(fused) < 3:
        return float("nan"), float("nan")
    own = [fit_error(pair.p[rows_p], pair.truth[pair.log_ids_p[rows_p]])["rmse"],
           fit_error(pair.q[rows_q], pair.truth[pair.log_ids_q[rows_q]])["rmse"]]
    return fit_error(fused[["x", "y"]].to_numpy(), pair.truth[pair.log_ids_p[rows_p]])["rmse"], min(own)


def own_fit_error(merged: pd.DataFrame, pair, theta: float) -> float:
    """Rotation error (deg) of a merge against the rigid fit by ids over the pairs it got right.

    On a non-rigid map pair the fit over all common trees is an average; a
    merge that is right for the trees it paired is right by this measure."""
    _, rows_p, rows_q = _fused_rows(merged)
    right = pair.ids_p[rows_p] == pair.ids_q[rows_q]
    if right.sum() < 3:
        return float("nan")
    fit = align_pairs(pair.p[rows_p[right]], pair.q[rows_q[right]], 1.0)
    return float(np.degrees(np.abs(wrap_angle(theta - fit.theta))))


def table(trials: pd.DataFrame, examples: pd.DataFrame) -> pd.DataFrame:
    # Covariances change the consensus methods' gates and every method's fusion; runs of the
    # other methods with them differ only in the fused positions.
    trials = trials[~trials.use_cov | trials.method.isin(CONSENSUS_METHODS)].copy()
    trials["ms"] = 1e3 * (trials.time_match_s + trials.time_merge_s)
    for (cut, source), rows in trials.groupby(["cut", "source"]):
        q, pair = quality(int(cut), source)
        trials.loc[rows.index, "map_rmse_p"] = q["p"]["rmse"]
        trials.loc[rows.index, "map_rmse_q"] = q["q"]["rmse"]
        trials.loc[rows.index, ["oracle_correct", "oracle_wrong", "oracle_wrong_few", "transform_oracle_correct",
                                "transform_oracle_wrong"]] = oracle_pairs(pair)
        for i, row in rows.iterrows():
            ex = examples[(examples.cut == cut) & (examples.source == source) & (examples.method == row.method)
                          & (examples.use_cov == row.use_cov) & (examples.kind == "merged")]
            trials.loc[i, ["fused_rmse", "agents_rmse"]] = fused_vs_agents(ex, pair) if row.matched else np.nan
            trials.loc[i, "rot_err_own_deg"] = own_fit_error(ex, pair, row.theta) if row.matched else np.nan
            _, rows_p, rows_q = _fused_rows(ex)
            trials.loc[i, "wrong_few"] = wrong_on_few_sightings(pair, rows_p, rows_q)
    t = trials[list(COLUMNS)].sort_values(["source", "cut", "method", "use_cov"])
    return t.rename(columns=COLUMNS)


def figure(examples: pd.DataFrame, out: Path, cut: int = DEFAULT_CUT, method: str = "consensus") -> list[Path]:
    """Agent maps in their own frames, and the merged map on the reference trees (one row per source)."""
    sources = sorted(examples.source.unique())
    rows_label = {"reference": "trees on the reference trajectory", "slam": "each agent's own SLAM map"}
    colours = {"fused": "tab:green", "p": "tab:blue", "q": "tab:orange"}
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(len(sources), 3, figsize=(7.5, 2.6 * len(sources)), squeeze=False,
                                 layout="constrained", gridspec_kw={"width_ratios": [1.0, 1.0, 1.25]})
        for row, source in zip(axes, sources):
            ex = examples[(examples.cut == cut) & (examples.source == source)
                          & (examples.method == method) & ~examples.use_cov]
            for ax, kind, title in zip(row[:2], ("p", "q"), (f"agent p: poses before {cut}",
                                                               f"agent q: poses from {cut} on")):
                pts = ex[ex.kind == kind]
                ax.scatter(pts.x, pts.y, s=5, c=colours[kind])
                ax.set_title(f"{title}\n{len(pts)} trees, its own frame", fontsize=7)
            row[0].set_ylabel(f"{rows_label.get(source, source)}\ny (m)")
            ax = row[2]
            truth, merged = ex[ex.kind == "truth"], ex[ex.kind == "merged"]
            ax.scatter(truth.x, truth.y, marker="+", s=22, c="k", lw=0.6, label="reference trees")
            for origin, colour in colours.items():
                sel = merged[merged.origin == origin]
                ax.scatter(sel.x, sel.y, marker="s", s=9, facecolors="none", edgecolors=colour,
                           lw=0.6, label=f"merged, {origin} ({len(sel)})")
            ax.set_title(f"{method} merge on the reference trees\nin p's frame", fontsize=7)
            ax.legend(fontsize=5.5, frameon=False, loc="upper left", bbox_to_anchor=(1.0, 1.0))
            for a in row:
                a.set_aspect("equal", adjustable="datalim")
                a.tick_params(labelsize=6)
        for a in axes[-1]:
            a.set_xlabel("x (m)")
        fig.suptitle(f"Victoria Park split at pose {cut}: two agents' maps and their merge", fontsize=8)
        return save_figure(fig, out, "victoria_park")


def bent_figure(out: Path, cut: int = 5500) -> list[Path]:
    """A bent late map: the default method's merge and the second rigid match ``residual_match`` finds among the
    trees it left unpaired, on the reference trees (slam source, with the agents' covariances)."""
    _, pair = quality(cut, "slam")
    cov = {"cov_p": pair.cov_p, "cov_q": pair.cov_q}
    first = merge_maps(pair.p, pair.q, pair.sigma, **cov)
    second = residual_match(pair.p, pair.q, first, pair.sigma, **cov)
    # The reference trees in p's frame: the rigid fit of the reference onto p's trees by id.
    onto_p = align_pairs(pair.truth[pair.log_ids_p], pair.p, 1.0)
    truth = rotate(onto_p.theta, pair.truth) + onto_p.t
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(4.6, 4.6), layout="constrained")
        ax.scatter(truth[:, 0], truth[:, 1], marker="+", s=22, c="k", lw=0.6, label="reference trees")
        for pairs, colour, label in (
                (first.pairs, "tab:green", f"merge ({len(first.pairs)} pairs)"),
                (second.pairs, "tab:red", f"second match ({len(second.pairs)} pairs, "
                                          f"{np.degrees(second.rotation_offset):+.1f}°)")):
            if not len(pairs):
                continue
            ax.scatter(*pair.p[pairs[:, 0]].T, marker="o", s=12, facecolors="none", edgecolors=colour, lw=0.7,
                       label=f"{label}: p's tree")
            ax.scatter(*rotate(-first.theta, pair.q[pairs[:, 1]] - first.t).T, marker="s", s=10, c=colour,
                       lw=0, alpha=0.6, label="   its partner in q, placed by the merge")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m), p's frame")
        ax.set_ylabel("y (m)")
        ax.legend(fontsize=5.5, frameon=False, loc="upper right", bbox_to_anchor=(1.0, 0.74))
        ax.set_title(f"Victoria Park split at pose {cut}, SLAM maps: q's map is bent,\nthe merge aligns its "
                     "larger part; the trees it left unpaired hold a second match", fontsize=7)
        return save_figure(fig, out, "victoria_park_bent")


#: The preset's cuts, for the tables on the SLAM maps beyond the sweep's.
SLAM_CUTS = (1500, 2500, 3483, 4500, 5500, 6200)
#: Landmark-confirmation thresholds of ``confirmation_table``.
CONFIRMATION_SIGHTINGS = (1, 2, 3)


def confirmation_table() -> pd.DataFrame:
    """The default method on the SLAM maps when each agent publishes only trees it sighted at least k times."""
    rows = []
    for cut in SLAM_CUTS:
        for k in CONFIRMATION_SIGHTINGS:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # map quality is in the main table
                pair = victoria_park(cut=cut, source="slam", min_sightings=k)
            for use_cov in (False, True):
                cov = {"cov_p": pair.cov_p, "cov_q": pair.cov_q} if use_cov else {}
                res = merge_maps(pair.p, pair.q, pair.sigma, **cov)
                err = map_errors(pair, res)
                merged = pd.DataFrame({"origin": res.combined.origin, "index_p": res.combined.index_p,
                                       "index_q": res.combined.index_q, "x": res.combined.points[:, 0],
                                       "y": res.combined.points[:, 1]})
                fused, agents = fused_vs_agents(merged, pair) if res.matched else (np.nan, np.nan)
                rows.append({"cut": cut, "min sightings": k, "covariances": use_cov, "trees p": len(pair.p),
                             "trees q": len(pair.q), "common": pair.n_common, "matched": res.matched,
                             "correct": err["correct_pairs"], "wrong": err["wrong_pairs"],
                             "wrong (% of pairs)": 100 * err["wrong_pairs"] / max(err["n_pairs"], 1),
                             "rot err (deg)": err["rot_err_deg"] if res.matched else np.nan,
                             "fused RMSE (m)": fused, "better agent, same trees (m)": agents})
    return pd.DataFrame(rows)


def rigidity_table(sources) -> pd.DataFrame:
    """The default method (with the agents' covariances on the slam source), then ``residual_match`` on the
    trees it left unpaired: a second significant rigid match says, from the maps alone, that one map is bent."""
    rows = []
    for source in sources:
        for cut in SLAM_CUTS:
            _, pair = quality(cut, source)
            cov = {"cov_p": pair.cov_p, "cov_q": pair.cov_q} if source == "slam" else {}
            first = merge_maps(pair.p, pair.q, pair.sigma, **cov)
            err = map_errors(pair, first)
            row = {"cut": cut, "source": source, "covariances": bool(cov), "matched": first.matched,
                   "pairs": len(first.pairs), "correct": err["correct_pairs"],
                   "rot err (deg)": err["rot_err_deg"] if first.matched else np.nan}
            if first.matched:
                second = residual_match(pair.p, pair.q, first, pair.sigma, **cov)
                right = pair.ids_p[second.pairs[:, 0]] == pair.ids_q[second.pairs[:, 1]]
                row.update({"second match": second.matched, "its pairs": len(second.pairs),
                            "its correct": int(right.sum()),
                            "its rotation against the first (deg)": np.degrees(second.rotation_offset)})
            rows.append(row)
    return pd.DataFrame(rows)


def solver_check() -> pd.DataFrame:
    """The SLAM solver on the whole drive against the reference tree map (rigid fit by tree id)."""
    log = load_log()
    ids, points, _ = slam_map()
    return pd.DataFrame([{"poses": len(log.pose_ids), "trees": len(ids), **fit_error(points, log.trees[ids])}])


#: Solver settings other than the defaults that ``solver_settings_table`` tries.
SOLVER_VARIANTS = {
    "GTSAM load2D's sighting noise": {"sighting_noise": "load2d"},
    "relinearise at every pose": {"relinearize_skip": 1},
    "no batch refinement": {"batch_refinement": False},
    "Huber kernel on sightings": {"sighting_kernel": "huber"},
}


def solver_settings_table() -> pd.DataFrame:
    """Each agent's map error (RMSE after the fit by tree id, m) with the default solver and each variant."""
    log = load_log()
    # The solver's own settings; load2D's rule changes the model, not how it is solved.
    solver_only = [name for name, v in SOLVER_VARIANTS.items() if "sighting_noise" not in v]
    rows = []
    for cut in SLAM_CUTS:
        for agent, (start, stop) in (("p", (0, cut)), ("q", (cut, None))):
            row = {"cut": cut, "agent": agent}
            for name, settings in {"default": {}, **SOLVER_VARIANTS}.items():
                ids, points, _ = slam_map(start, stop, solver=settings)
                row[name] = fit_error(points, log.trees[ids])["rmse"]
            row["largest change, solver settings"] = max(abs(row[name] - row["default"]) for name in solver_only)
            rows.append(row)
    return pd.DataFrame(rows)


def write(sweep: Path, out: Path) -> list[Path]:
    trials, examples = load_runs(sweep)
    out.mkdir(parents=True, exist_ok=True)
    paths = [*save_table(table(trials, examples), out / "table"), *figure(examples, out),
             *save_table(rigidity_table(sorted(trials.source.unique())), out / "rigidity")]
    if (trials.source == "slam").any():
        paths += bent_figure(out)
        paths += save_table(solver_check(), out / "solver_check")
        paths += save_table(solver_settings_table(), out / "solver_settings")
        paths += save_table(confirmation_table(), out / "min_sightings")
    return paths


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Merge two agents' Victoria Park maps with every matcher.")
    parser.add_argument("--out", default="results/victoria_park")
    parser.add_argument("--tables", action="store_true", help="only rebuild table and figure")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides")
    args = parser.parse_args(argv)
    if not args.tables:
        sources = ["reference"] + (["slam"] if importlib.util.find_spec("gtsam") else [])
        methods = ["paper", "cyclic", *CONSENSUS_METHODS, "groth"]
        methods += ["astroalign"] if importlib.util.find_spec("astroalign") else []
        run_module(["experiments.run", "-m", "experiment=victoria_park", "mc.progress=false",
               f"scenario.source={','.join(sources)}", f"matcher.method={','.join(methods)}",
               f"aggregate_dir={SWEEP / 'aggregate'}", *args.overrides])
    for path in write(SWEEP, Path(args.out)):
        print(path)


if __name__ == "__main__":
    main()
