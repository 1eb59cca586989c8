"""Compare matchers side by side on the same trials (results/compare/).

    python -m experiments.compare            # presets compare (+ compare_astroalign if installed)
    python -m experiments.compare --tables   # only rebuild tables and figure from results/compare

Runs the ``compare`` sweep (paper, cyclic, consensus and Groth's voting on
the paper's Fig. 1 scenario, 100 landmarks and 75 % common, in both
layouts: the paper's strip and the interleaved layout where each agent
detects an overlap landmark with probability 0.9; 0-40 dB in 2.5 dB steps,
300 related and 300 unrelated map pairs per cell), ``compare_search`` (the
global search on the same trials) and, when astroalign is installed,
``compare_astroalign``; then writes, per scenario, ``compare.md`` /
``compare.csv``: method x SNR with triangle detection (TP / common, and the
part declared by the GLRT test alone) and false positives per trial,
correct and wrong landmark pairs per trial next to the oracle association's
(the best any matcher could do: it knows the true transform), merge success
(rotation error < 1° and combined-map RMSE < 2σ), transform found (rotation
< 1° and registration error <= σ), false merges on unrelated pairs and the
median time per merge; and ``success.png`` / ``.pdf``: transform found and
wrong pairs vs SNR per method and layout, with the oracle association's
wrong pairs and, when ``results/detector/limit.csv`` exists (``python -m
experiments.detector``), the exhaustive ML detector's transform-found curve.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from .aggregate import markdown, save_table, with_timing  # noqa: E402
from .figures import STYLE, _save  # noqa: E402
from .paper import _call  # noqa: E402

KEYS = ["n_landmarks", "overlap", "layout", "snr_db", "method", "tau"]


def comparison_table(table: pd.DataFrame) -> pd.DataFrame:
    """One row per (scenario, method, τ rule, SNR) joining related and unrelated cells."""
    related = table[~table.unrelated.astype(bool)]
    unrelated = table[table.unrelated.astype(bool)][KEYS + ["n_trials", "false_merge_rate"]]
    out = related.merge(unrelated, on=KEYS, how="left", suffixes=("", "_unrelated"))
    out["fp_per_trial"] = out.fp / out.n_trials
    # astroalign and the search return matched points, not triangles: no triangle counts.
    out.loc[out.method.isin(["astroalign", "search"]), ["recall_common", "recall_glrt", "fp_per_trial"]] = float("nan")
    out["false_merges"] = (out.false_merge_rate_unrelated * out.n_trials_unrelated).round()
    cols = KEYS + ["n_trials", "recall_common", "recall_glrt", "fp_per_trial", "correct_per_trial",
                   "wrong_per_trial", "oracle_correct_per_trial", "oracle_wrong_per_trial", "landmark_precision",
                   "landmark_recall", "success_rate", "found_rate", "false_merges", "n_trials_unrelated",
                   "median_ms_per_merge"]
    return out[[c for c in cols if c in out]].sort_values(["n_landmarks", "overlap", "layout", "method", "tau",
                                                           "snr_db"])


def success_figure(comp: pd.DataFrame, out: Path, limit: pd.DataFrame | None = None) -> list[Path]:
    """Transform found and wrong pairs per trial vs SNR, one column per layout, one line per method and τ rule;
    ``limit`` (``experiments.detector``'s table) adds the exhaustive ML detector's curve."""
    layouts = sorted(comp.layout.unique(), key=lambda s: s != "strip")
    colour = {m: f"C{k}" for k, m in enumerate(METHOD_ORDER)}
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(2, len(layouts), figsize=(3.4 * len(layouts), 5.6), sharex=True, squeeze=False)
        for col, layout in enumerate(layouts):
            part = comp[comp.layout == layout]
            top, bottom = axes[0, col], axes[1, col]
            for (method, tau), g in part.groupby(["method", "tau"], sort=True):
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
            if "oracle_wrong_per_trial" in part:
                # Same trials for every method: the oracle's curve is one.
                oracle = part.groupby("snr_db").oracle_wrong_per_trial.first()
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
        fig.suptitle(f"{n} landmarks per map, {ov:.0%} common; τ oracle (dashed) is a limit of the LP")
        # One legend for the figure: every line of every panel, once.
        named = {}
        for ax in axes.ravel():
            for h, lab in zip(*ax.get_legend_handles_labels()):
                named.setdefault(lab, h)
        fig.legend(named.values(), named.keys(), loc="lower center", ncol=3, frameon=False, fontsize=6)
        fig.tight_layout(rect=(0, 0.1, 1, 1))
        return _save(fig, out, "success")


def write_tables(out: Path) -> list[Path]:
    tables = sorted(out.glob("*/table.csv"))
    if not tables:
        raise FileNotFoundError(f"no */table.csv below {out}: run without --tables first")
    table = pd.concat([with_timing(t) for t in tables], ignore_index=True)
    comp = comparison_table(table)
    detector = out.parent / "detector" / "limit.csv"
    limit = pd.read_csv(detector) if detector.exists() else None
    return [*save_table(comp, out / "compare"), summary(comp, out / "summary.md"), *success_figure(comp, out, limit)]


#: Methods in the order the summary lists them: the paper, its variants, the baselines.
METHOD_ORDER = ["paper", "cyclic", "consensus", "search", "groth", "astroalign"]


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
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for every sweep")
    args = parser.parse_args(argv)
    out = Path(args.out)
    if not args.tables:
        presets = ["compare", "compare_search"]
        if importlib.util.find_spec("astroalign") is not None:
            presets.append("compare_astroalign")
        for preset in presets:
            _call(["experiments.run", "-m", f"experiment={preset}", f"aggregate_dir={out / preset}",
                   "mc.progress=false", *args.overrides])
    for path in write_tables(out):
        print(path)


if __name__ == "__main__":
    main()
