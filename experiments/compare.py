"""Compare matchers side by side on the same trials (results/compare/).

    python -m experiments.compare                    # every preset below, then tables and figure
    python -m experiments.compare --presets compare_search   # some presets only (the others' tables stay)
    python -m experiments.compare --tables           # only rebuild tables and figure from results/compare

On the paper's Fig. 1 scenario (100 landmarks, 75 % common) in both layouts
(the paper's strip, and the interleaved layout where each agent detects an
overlap landmark with probability 0.9), 0-40 dB in 2.5 dB steps, related
and unrelated map pairs, with the oracle association on every trial, runs
the sweeps ``compare`` (paper, cyclic and Groth's voting; 300 pairs per
cell), ``compare_consensus`` (consensus, 1,000 pairs per cell: the
low-SNR targets are judged on it), ``compare_search`` (the global search
alone, 300), when astroalign is installed, ``compare_astroalign``, and
``compare_association`` (consensus at 2.5 and 5 dB, 10,000 related pairs per
layout: at 1,000 its transform is found in too few pairs to judge the
association there). A cell's seeds depend on the scenario only, so every
method sees the same maps. Then writes:

* ``compare.md`` / ``.csv``: method x SNR with triangle detection (TP /
  common, and the part declared by the GLRT test alone) and false
  positives per trial, correct and wrong landmark pairs per trial next to
  the oracle association's (the best any matcher could do: it knows the
  true transform), merge success (rotation error < 1° and combined-map RMSE
  < 2σ), transform found (rotation < 1° and registration error <= σ),
  false merges on unrelated pairs and the median time per merge;
* ``summary.md``: the same at 10-40 dB in 10 dB steps;
* ``found.md`` / ``.csv``: consensus and the search alone, transform found
  with its 95 % Wilson interval, false merges, and correct and wrong
  landmark pairs on the pairs whose transform was found against two
  oracles: the oracle association (true transform and true prior π) and
  the transform oracle (true transform only; π estimated as consensus
  does), every SNR;
* ``crossing.md`` / ``.csv`` (when ``results/detector/limit.csv`` exists,
  ``python -m experiments.detector``): the SNR at which each method and
  the exhaustive ML detector find 90 % of the transforms, and at which the
  ML transform (no threshold) and the fit knowing every correspondence are
  within 1° and σ in 90 % of the pairs;
* ``association.md`` / ``.csv``: from ``compare_association``, the
  association on the found pairs against both oracles' (as in ``found.md``),
  with 95 % intervals of the ratios to the oracle's from the found pairs'
  own counts (kept in ``compare_association/found_pairs.csv``, as the
  sweep's trial files are not);
* ``success.png`` / ``.pdf``: transform found and wrong pairs vs SNR per
  method and layout, with the oracle association's wrong pairs, the
  detector's transform-found curve and the fit knowing every correspondence.
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from .aggregate import markdown, runs_since, save_table, with_timing  # noqa: E402
from .figures import STYLE, legend_entries, save_figure  # noqa: E402
from .intervals import ratio_interval, wilson  # noqa: E402
from .paper import run_module  # noqa: E402

#: The sweeps of the experiment: each writes ``<out>/<preset>/table.csv``.
PRESETS = ("compare", "compare_consensus", "compare_search", "compare_astroalign", "compare_cpd", "compare_clipper",
           "compare_teaser", "compare_association")
#: The optional modules each preset's methods need: without them the preset is skipped.
PRESET_NEEDS = {"compare_astroalign": ("astroalign",), "compare_cpd": ("pycpd",), "compare_clipper": ("clipperpy",),
                "compare_teaser": ("teaserpp_python",)}
#: The outside peers (``compare_cpd``, ``compare_clipper``, ``compare_teaser``): drawn in ``peers.png`` rather than ``success.png``.
PEERS = ("cpd", "clipper", "teaser")
#: Methods that return landmark pairs, not triangle pairs: no triangle counts.
NO_TRIANGLES = ("astroalign", "search", *PEERS)
#: The preset with many pairs at low SNR: tabulated on its own (``association.md``), not in the comparison.
ASSOCIATION = "compare_association"
#: Where its sweep runs; the found pairs of the runs it aggregated are kept (``found_pairs.csv``) for the intervals.
ASSOCIATION_SWEEP = Path("outputs/sweeps") / ASSOCIATION
#: Per found map pair: the method's correct and wrong landmark pairs and both oracles'.
PAIR_COUNTS = ["correct_pairs", "wrong_pairs", "oracle_correct_pairs", "oracle_wrong_pairs",
               "transform_oracle_correct_pairs", "transform_oracle_wrong_pairs"]
KEYS = ["n_landmarks", "overlap", "layout", "snr_db", "method", "tau"]


def comparison_table(table: pd.DataFrame) -> pd.DataFrame:
    """One row per (scenario, method, τ rule, SNR) joining related and unrelated cells."""
    related = table[~table.unrelated.astype(bool)]
    unrelated = table[table.unrelated.astype(bool)][KEYS + ["n_trials", "false_merge_rate"]]
    out = related.merge(unrelated, on=KEYS, how="left", suffixes=("", "_unrelated"))
    out["fp_per_trial"] = out.fp / out.n_trials
    out.loc[out.method.isin(NO_TRIANGLES), ["recall_common", "recall_glrt", "fp_per_trial"]] = float("nan")
    out["false_merges"] = (out.false_merge_rate_unrelated * out.n_trials_unrelated).round().astype("Int64")
    out["n_trials_unrelated"] = out.n_trials_unrelated.astype("Int64")
    cols = KEYS + ["n_trials", "recall_common", "recall_glrt", "fp_per_trial", "correct_per_trial",
                   "wrong_per_trial", "oracle_correct_per_trial", "oracle_wrong_per_trial", "landmark_precision",
                   "landmark_recall", "success_rate", "found_rate", "correct_vs_oracle_found",
                   "wrong_vs_oracle_found", "correct_vs_transform_oracle_found", "wrong_vs_transform_oracle_found",
                   "false_merges", "n_trials_unrelated",
                   "median_ms_per_merge"]
    return out[[c for c in cols if c in out]].sort_values(["n_landmarks", "overlap", "layout", "method", "tau",
                                                           "snr_db"])


def success_figure(comp: pd.DataFrame, out: Path, limit: pd.DataFrame | None = None, *, name: str = "success",
                   curves=None, references=("ml_accurate_rate", "correspondence_found_rate"),
                   note: str = "τ oracle (dashed) is a limit of the LP") -> list[Path]:
    """Transform found and wrong pairs per trial vs SNR, one column per layout, one line per method and τ rule
    (only the (method, τ rule) pairs ``curves``, when given); ``limit`` (``experiments.detector``'s table) adds
    the exhaustive ML detector's curve and those of its columns ``references``."""
    layouts = sorted(comp.layout.unique(), key=lambda s: s != "strip")
    colour = {m: f"C{k}" for k, m in enumerate(METHOD_ORDER)}
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(2, len(layouts), figsize=(3.4 * len(layouts), 5.6), sharex=True, squeeze=False)
        for col, layout in enumerate(layouts):
            part = comp[comp.layout == layout]
            top, bottom = axes[0, col], axes[1, col]
            for (method, tau), g in part.groupby(["method", "tau"], sort=True):
                if curves is not None and (method, tau) not in curves:
                    continue
                label = method if tau == "none" else f"{method}, τ {tau}"
                style = {"color": colour.get(method, "C9"), "marker": "o", "ms": 2.5, "label": label,
                         **({"ls": "--", "alpha": 0.5} if tau == "oracle" else {}),
                         # consensus falls back on the search: drawn thin, it shows where they differ.
                         **({"lw": 0.7, "ms": 1.2} if method == "search" else {})}
                top.plot(g.snr_db, g.found_rate, **style)
                bottom.plot(g.snr_db, g.wrong_per_trial, **style)
            if limit is not None and (limit.layout == layout).any():
                lim = limit[limit.layout == layout]
                top.plot(lim.snr_db, lim.found_rate, color="k", lw=1.4, ls=":",
                         label="limit: exhaustive ML detector (true σ)")
                if "ml_accurate_rate" in lim and "ml_accurate_rate" in references:
                    top.plot(lim.snr_db, lim.ml_accurate_rate, color="0.5", lw=1.0, ls=":",
                             label="ML transform accurate, no threshold")
                if "correspondence_found_rate" in lim and "correspondence_found_rate" in references:
                    top.plot(lim.snr_db, lim.correspondence_found_rate, color="0.3", lw=1.0, ls="--",
                             label="limit: ML fit knowing every correspondence")
            if "oracle_wrong_per_trial" in part:
                # Same trials for every method: the oracle's curve is one.
                oracle = part.sort_values("n_trials", ascending=False).groupby("snr_db").oracle_wrong_per_trial.first()
                bottom.plot(oracle.index, oracle.to_numpy(), color="k", lw=1.4, ls="-.",
                            label="limit: oracle association (true transform)")
            top.set_title(f"{layout} layout")
            top.set_ylabel("transform found")
            top.set_ylim(-0.02, 1.02)
            bottom.set_ylabel("wrong landmark pairs per trial")
            bottom.set_yscale("symlog", linthresh=0.1)
            bottom.set_ylim(0, 150)
            bottom.set_xlabel("SNR (dB)")
            for ax in (top, bottom):
                ax.grid(alpha=0.3, lw=0.4)
        n, ov = comp.n_landmarks.iloc[0], comp.overlap.iloc[0]
        fig.suptitle(f"{n} landmarks per map, {ov:.0%} common; {note}")
        fig.legend(*legend_entries(axes), loc="lower center", ncol=3, frameon=False, fontsize=6)
        fig.tight_layout(rect=(0, 0.1, 1, 1))
        return save_figure(fig, out, name)


def write_tables(out: Path) -> list[Path]:
    paths = []
    if (out / ASSOCIATION / "table.csv").exists():
        found = out / ASSOCIATION / "found_pairs.csv"
        paths += save_table(association_table(pd.read_csv(out / ASSOCIATION / "table.csv"),
                                              pd.read_csv(found) if found.exists() else None), out / "association")
    tables = sorted(t for t in out.glob("*/table.csv") if t.parent.name != ASSOCIATION)
    if not tables:
        if paths:  # the association sweep alone
            return paths
        raise FileNotFoundError(f"no */table.csv below {out}: run without --tables first")
    table = pd.concat([with_timing(t) for t in tables], ignore_index=True)
    comp = keep_timings(comparison_table(table), out / "compare.csv")
    detector = out.parent / "detector" / "limit.csv"
    limit = pd.read_csv(detector) if detector.exists() else None
    if limit is not None and "n_landmarks" in limit:  # the detector's rows of the compared maps' size only
        limit = limit[limit.n_landmarks.isin(comp.n_landmarks.unique())]
    ours = comp[~comp.method.isin(PEERS)]
    paths += [*save_table(comp, out / "compare"), summary(comp, out / "summary.md"), *success_figure(ours, out, limit)]
    if comp.method.isin(PEERS).any():
        # Six curves a panel: consensus, the paper, the three peers and the detector's limit.
        curves = {("consensus", "chi2:0.01"), ("paper", "chi2:0.01"), *((peer, "none") for peer in PEERS)}
        paths += success_figure(comp, out, limit, name="peers", curves=curves, references=(),
                                note="consensus, the paper and the outside peers")
    paths += save_table(found_table(comp), out / "found")
    if limit is not None:
        paths += save_table(crossing(comp, limit), out / "crossing")
    return paths


def keep_timings(comp: pd.DataFrame, previous: Path) -> pd.DataFrame:
    """Times missing from ``comp`` (git keeps no ``timing.csv``: tables rebuilt
    from a clone) taken from the ``compare.csv`` last written, so that
    ``--tables`` on a clone rewrites the same files."""
    if not previous.is_file() or comp.median_ms_per_merge.notna().all():
        return comp
    keys = ["n_landmarks", "overlap", "layout", "snr_db", "method", "tau"]
    old = pd.read_csv(previous).set_index(keys).median_ms_per_merge
    missing = comp.median_ms_per_merge.isna()
    at = pd.MultiIndex.from_frame(comp.loc[missing, keys])
    comp.loc[missing, "median_ms_per_merge"] = old.reindex(at).to_numpy()
    return comp


def found_pairs(runs) -> pd.DataFrame:
    """One row per map pair whose transform was found in the given runs (cell directories with a
    ``trials.parquet``): layout, SNR, trial and ``PAIR_COUNTS``."""
    trials = pd.concat([pd.read_parquet(Path(r) / "trials.parquet") for r in runs], ignore_index=True)
    found = trials[trials.transform_found.astype(bool) & (trials.tau != "oracle")]
    return found[["layout", "snr_db", "trial", *PAIR_COUNTS]].sort_values(["layout", "snr_db", "trial"])


def association_table(table: pd.DataFrame, pairs: pd.DataFrame | None = None) -> pd.DataFrame:
    """``association.md``: the landmark association on the pairs whose transform was found, against both
    oracles', from a sweep with enough pairs to find some where transforms are rarely found; with
    ``pairs`` (``found_pairs``), the 95 % intervals of the ratios to the oracle's."""
    t = table[table.tau != "oracle"].copy()
    t["found_pairs"] = np.round(t.found_rate * t.n_trials).astype(int)
    if pairs is not None:
        def interval(x, y):
            low, high = ratio_interval(x, y)
            return f"{low:.3f}-{high:.3f}" if np.isfinite(low) else None

        rows = [{"layout": layout, "snr_db": snr,
                 **{f"{kind}_interval": interval(g[f"{kind}_pairs"], g[f"oracle_{kind}_pairs"])
                    for kind in ("correct", "wrong")}}
                for (layout, snr), g in pairs.groupby(["layout", "snr_db"])]
        t = t.merge(pd.DataFrame(rows, columns=["layout", "snr_db", "correct_interval", "wrong_interval"]),
                    on=["layout", "snr_db"], how="left")
    names = {"method": "method", "layout": "layout", "snr_db": "SNR", "n_trials": "pairs",
             "found_pairs": "transform found (pairs)",
             "correct_vs_oracle_found": "correct vs oracle (found)", "correct_interval": "correct: 95 % interval",
             "wrong_vs_oracle_found": "wrong vs oracle (found)", "wrong_interval": "wrong: 95 % interval",
             "correct_vs_transform_oracle_found": "correct vs transform oracle (found)",
             "wrong_vs_transform_oracle_found": "wrong vs transform oracle (found)"}
    t = t.sort_values(["layout", "snr_db"], key=lambda c: c != "strip" if c.name == "layout" else c)
    return t[[c for c in names if c in t]].rename(columns=names)


#: Methods of ``found.md``: the ones meant to work where triangles stop discriminating, and the outside peers.
LOW_SNR_METHODS = ("consensus", "search", *PEERS)


def found_table(comp: pd.DataFrame) -> pd.DataFrame:
    """``found.md``: transform found with its 95 % Wilson interval, false merges and the association on found
    pairs against the two oracles' (``metrics.oracle_pairs_batch``), per method of
    ``LOW_SNR_METHODS``, layout and SNR (the low-SNR targets)."""
    s = comp[(comp.tau != "oracle") & comp.method.isin(LOW_SNR_METHODS)].copy()
    s["found_low"], s["found_high"] = wilson(np.round(s.found_rate * s.n_trials), s.n_trials)
    s["false_high"] = wilson(s.false_merges, s.n_trials_unrelated)[1]
    names = {"method": "method", "layout": "layout", "snr_db": "SNR", "n_trials": "pairs",
             "found_rate": "transform found", "found_low": "95 % low", "found_high": "95 % high",
             "false_merges": "false merges", "n_trials_unrelated": "unrelated pairs",
             "false_high": "false-merge rate, 95 % high",
             "correct_vs_oracle_found": "correct vs oracle (found)", "wrong_vs_oracle_found": "wrong vs oracle (found)",
             "correct_vs_transform_oracle_found": "correct vs transform oracle (found)",
             "wrong_vs_transform_oracle_found": "wrong vs transform oracle (found)",
             "median_ms_per_merge": "ms per merge"}
    s["order"] = s.method.map({m: k for k, m in enumerate(METHOD_ORDER)})
    s = s.sort_values(["order", "layout", "snr_db"], key=lambda c: c != "strip" if c.name == "layout" else c)
    return s[[c for c in names if c in s]].rename(columns=names)


#: The transform-found rate whose SNR is compared with the exhaustive detector's.
CROSSING_LEVEL = 0.9


def crossing_snr(snr, rate, level: float = CROSSING_LEVEL) -> float:
    """First SNR where ``rate`` reaches ``level``, linear between grid points (nan if never)."""
    snr, rate = np.asarray(snr, float), np.asarray(rate, float)
    above = np.flatnonzero(rate >= level)
    if not len(above):
        return float("nan")
    k = above[0]
    if k == 0:
        return float(snr[0])
    return float(snr[k - 1] + (level - rate[k - 1]) * (snr[k] - snr[k - 1]) / (rate[k] - rate[k - 1]))


#: Other references in the detector's table: column -> name in ``crossing.md``.
LIMIT_CURVES = {"ml_accurate_rate": "reference: ML transform, no threshold",
                "correspondence_found_rate": "limit: ML fit knowing every correspondence"}


def crossing(comp: pd.DataFrame, limit: pd.DataFrame) -> pd.DataFrame:
    """``crossing.md``: per layout and method, the SNR at which ``CROSSING_LEVEL`` of the transforms are
    found, interpolated linearly between grid SNRs, and how far it lies behind the exhaustive detector's."""
    rows = []
    usable = comp[comp.tau != "oracle"]
    for layout, lim in limit.groupby("layout", sort=False):
        lim = lim.sort_values("snr_db")
        detector = crossing_snr(lim.snr_db, lim.found_rate)
        rows.append({"layout": layout, "method": "limit: exhaustive detector", "snr_db": detector,
                     "behind_detector_db": 0.0})
        for column, name in LIMIT_CURVES.items():
            if column in lim:
                at = crossing_snr(lim.snr_db, lim[column])
                rows.append({"layout": layout, "method": name, "snr_db": at, "behind_detector_db": at - detector})
        for (method, tau), g in usable[usable.layout == layout].groupby(["method", "tau"], sort=False):
            g = g.sort_values("snr_db")
            at = crossing_snr(g.snr_db, g.found_rate)
            rows.append({"layout": layout, "method": method, "tau": tau, "snr_db": at,
                         "behind_detector_db": at - detector})
    names = {"layout": "layout", "method": "method", "tau": "tau", "snr_db": f"SNR at {CROSSING_LEVEL:.0%} found",
             "behind_detector_db": "behind the detector (dB)"}
    return pd.DataFrame(rows)[list(names)].rename(columns=names)


#: Methods in the order the summary lists them: the paper, its variants, the baselines.
METHOD_ORDER = ["paper", "cyclic", "consensus", "search", "groth", "astroalign", *PEERS]


def summary(comp: pd.DataFrame, path: Path) -> Path:
    """The README's table: 10-40 dB in 10 dB steps, usable τ rules, methods in ``METHOD_ORDER``, plain names."""
    # The oracle τ rule (a limit of the paper's LP, not a usable threshold) stays in compare.md.
    s = comp[comp.snr_db.isin([10, 20, 30, 40]) & (comp.tau != "oracle")].copy()
    s["order"] = s.method.map({m: k for k, m in enumerate(METHOD_ORDER)})
    s = s.sort_values(["layout", "order", "tau", "snr_db"], key=lambda c: c != "strip" if c.name == "layout" else c)
    names = {"layout": "layout", "method": "method", "tau": "tau", "snr_db": "SNR",
             "recall_common": "triangle recall", "fp_per_trial": "triangle FP / trial",
             "correct_per_trial": "correct pairs / trial", "oracle_correct_per_trial": "oracle correct",
             "wrong_per_trial": "wrong pairs / trial", "oracle_wrong_per_trial": "oracle wrong",
             "success_rate": "merge success", "found_rate": "transform found",
             "false_merges": "false merges", "n_trials_unrelated": "unrelated pairs",
             "median_ms_per_merge": "ms per merge"}
    s = s[[c for c in names if c in s]].rename(columns=names)
    s["SNR"] = s["SNR"].astype(int)
    path.write_text(markdown(s))
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Compare matchers side by side.")
    parser.add_argument("--out", default="results/compare")
    parser.add_argument("--tables", action="store_true", help="only rebuild tables and figure")
    parser.add_argument("--presets", help=f"comma-separated presets to run (default: {', '.join(PRESETS)})")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for every sweep")
    args = parser.parse_args(argv)
    out = Path(args.out)
    presets = list(PRESETS) if args.presets is None else args.presets.split(",")
    if set(presets) - set(PRESETS):
        raise SystemExit(f"--presets: unknown {sorted(set(presets) - set(PRESETS))}; allowed: {', '.join(PRESETS)}")
    # A preset whose optional methods are not installed is skipped (docs/peers.md builds the peers).
    presets = [p for p in presets if all(importlib.util.find_spec(m) for m in PRESET_NEEDS.get(p, ()))]
    if not args.tables:
        for preset in presets:
            where = [f"hydra.sweep.dir={ASSOCIATION_SWEEP}"] if preset == ASSOCIATION else []
            started = time.time()
            run_module(["experiments.run", "-m", f"experiment={preset}", f"aggregate_dir={out / preset}",
                   "mc.progress=false", *args.overrides, *where])
            if preset == ASSOCIATION:  # the runs its aggregate holds, as the aggregation picked them
                found_pairs(runs_since(ASSOCIATION_SWEEP, started)).to_csv(out / preset / "found_pairs.csv",
                                                                           index=False)
    for path in write_tables(out):
        print(path)


if __name__ == "__main__":
    main()
