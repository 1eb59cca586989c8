"""Compare matchers side by side on the same trials (results/compare/).

    python -m experiments.compare            # presets compare (+ compare_astroalign if installed)
    python -m experiments.compare --tables   # only rebuild tables and figure from results/compare

Runs the ``compare`` sweep (paper, cyclic, consensus and Groth's voting on the
paper's Fig. 1 scenario at 10-40 dB, related and unrelated map pairs, 1,000
trials each) and, when astroalign is installed, ``compare_astroalign``; then
writes, per scenario, ``compare.md`` / ``compare.csv``: method x SNR with
triangle detection (TP / common) and false positives per trial, landmark
correspondence precision / recall, merge success rate (rotation error < 1°
and combined-map RMSE < 2σ), false merges on unrelated pairs and the median
time per merge; and ``success.png`` / ``.pdf``: merge success vs SNR per
method.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from .aggregate import CELL, markdown, save_table  # noqa: E402
from .figures import STYLE, _save  # noqa: E402
from .paper import _call  # noqa: E402

KEYS = ["n_landmarks", "overlap", "snr_db", "method", "tau"]


def comparison_table(table: pd.DataFrame) -> pd.DataFrame:
    """One row per (scenario, method, τ rule, SNR) joining related and unrelated cells."""
    related = table[~table.unrelated.astype(bool)]
    unrelated = table[table.unrelated.astype(bool)][KEYS + ["n_trials", "false_merge_rate"]]
    out = related.merge(unrelated, on=KEYS, how="left", suffixes=("", "_unrelated"))
    out["fp_per_trial"] = out.fp / out.n_trials
    # astroalign returns matched points, not triangles: no triangle counts.
    out.loc[out.method == "astroalign", ["recall_common", "fp_per_trial"]] = float("nan")
    out["false_merges"] = (out.false_merge_rate_unrelated * out.n_trials_unrelated).round()
    cols = KEYS + ["n_trials", "recall_common", "fp_per_trial", "landmark_precision",
                   "landmark_recall", "success_rate", "false_merges", "n_trials_unrelated",
                   "median_ms_per_merge"]
    return out[cols].sort_values(["n_landmarks", "overlap", "method", "tau", "snr_db"])


def success_figure(comp: pd.DataFrame, out: Path) -> list[Path]:
    """Merge success rate vs SNR, one line per method and τ rule."""
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(4.2, 3.2))
        for (method, tau), g in comp.groupby(["method", "tau"], sort=True):
            label = method if tau == "none" else f"{method}, τ {tau}"
            ax.plot(g.snr_db, g.success_rate, marker="o", ms=3,
                    ls="--" if tau == "oracle" else "-", label=label)
        ax.set_xlabel("SNR (dB)")
        ax.set_ylabel("merge success rate")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3, lw=0.4)
        ax.legend(frameon=False, fontsize=6)
        n, ov = comp.n_landmarks.iloc[0], comp.overlap.iloc[0]
        ax.set_title(f"{n} landmarks per map, {ov:.0%} common")
        fig.tight_layout()
        return _save(fig, out, "success")


def write_tables(out: Path) -> list[Path]:
    tables = sorted(out.glob("*/table.csv"))
    if not tables:
        raise FileNotFoundError(f"no */table.csv below {out}: run without --tables first")
    table = pd.concat([pd.read_csv(t).merge(pd.read_csv(t.with_name("timing.csv")), on=CELL + ["tau"])
                       for t in tables], ignore_index=True)
    comp = comparison_table(table)
    return [*save_table(comp, out / "compare"), summary(comp, out / "summary.md"), *success_figure(comp, out)]


#: Methods in the order the summary lists them: the paper, its variants, the baselines.
METHOD_ORDER = ["paper", "cyclic", "consensus", "groth", "astroalign"]


def summary(comp: pd.DataFrame, path: Path) -> Path:
    """The README's table: 20-40 dB, methods in ``METHOD_ORDER``, plain column names."""
    s = comp[comp.snr_db >= 20].copy()
    s["order"] = s.method.map({m: k for k, m in enumerate(METHOD_ORDER)})
    s = s.sort_values(["order", "tau", "snr_db"])
    names = {"method": "method", "tau": "tau", "snr_db": "SNR", "recall_common": "triangle recall",
             "fp_per_trial": "triangle FP / trial", "landmark_precision": "landmark precision",
             "landmark_recall": "landmark recall", "success_rate": "merge success",
             "false_merges": "false merges / 1,000 unrelated", "median_ms_per_merge": "ms per merge"}
    s = s[list(names)].rename(columns=names)
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
        presets = ["compare"]
        if importlib.util.find_spec("astroalign") is not None:
            presets.append("compare_astroalign")
        for preset in presets:
            _call(["experiments.run", "-m", f"experiment={preset}", f"aggregate_dir={out / preset}",
                   "mc.progress=false", *args.overrides])
    for path in write_tables(out):
        print(path)


if __name__ == "__main__":
    main()
