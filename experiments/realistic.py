"""Consensus on realistic maps against the oracle association (results/realistic/).

    python -m experiments.realistic            # the realistic preset, then the summary
    python -m experiments.realistic --tables   # only rebuild the summary from results/realistic

Runs the ``realistic`` sweep (100 landmarks per map, 75 common, interleaved
layout with p_detect 0.9; clutter 0 or 10 % of the landmarks per map;
isotropic or range-bearing-like noise with anisotropy 2; 20 and 30 dB;
1,000 related and 1,000 unrelated pairs per cell; consensus given the maps'
covariances) with the oracle association on every trial, and writes
``summary.md`` / ``summary.csv``: per cell, transform found, false merges
on the unrelated pairs, and correct and wrong landmark pairs per trial next
to the oracle association's, with their ratios (and the ratios to the
transform oracle, which knows the true transform but not the prior π).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from .aggregate import save_table
from .paper import run_module


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Related cells with their unrelated twins' false merges, plain column names."""
    keys = ["layout", "clutter", "anisotropy", "snr_db"]
    related = table[~table.unrelated.astype(bool)]
    unrelated = table[table.unrelated.astype(bool)].assign(
        false_merges=lambda t: (t.false_merge_rate * t.n_trials).round().astype(int))
    out = related.merge(unrelated[keys + ["false_merges", "n_trials"]], on=keys, suffixes=("", "_unrelated"))
    names = {"layout": "layout", "clutter": "clutter", "anisotropy": "anisotropy", "snr_db": "SNR",
             "n_trials": "pairs", "found_rate": "transform found", "false_merges": "false merges",
             "n_trials_unrelated": "unrelated pairs", "correct_per_trial": "correct / trial",
             "oracle_correct_per_trial": "oracle correct / trial", "correct_vs_oracle": "correct vs oracle",
             "wrong_per_trial": "wrong / trial", "oracle_wrong_per_trial": "oracle wrong / trial",
             "wrong_vs_oracle": "wrong vs oracle", "correct_vs_transform_oracle": "correct vs transform oracle",
             "wrong_vs_transform_oracle": "wrong vs transform oracle"}
    return out.sort_values(["snr_db", "clutter", "anisotropy"])[[c for c in names if c in out]].rename(columns=names)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Consensus on realistic maps against the oracle association.")
    parser.add_argument("--out", default="results/realistic")
    parser.add_argument("--tables", action="store_true", help="only rebuild the summary")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides")
    args = parser.parse_args(argv)
    out = Path(args.out)
    if not args.tables:
        run_module(["experiments.run", "-m", "experiment=realistic", f"aggregate_dir={out}", "mc.progress=false",
               *args.overrides])
    for path in save_table(summary(pd.read_csv(out / "table.csv")), out / "summary"):
        print(path)


if __name__ == "__main__":
    main()
