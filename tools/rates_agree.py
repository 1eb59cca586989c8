"""Do regenerated results agree with a committed revision's within their 95 % intervals?

    python tools/rates_agree.py [--base REV] [PATH ...]

For every CSV under the given paths (default ``results``) that differs from
its version at ``--base`` (default ``HEAD``), the rows of both versions are
joined on their configuration columns (``KEYS``), and every rate column (a
name matching ``RATE`` whose values lie in [0, 1]) is compared: the old rate
should lie inside the new rate's 95 % Wilson interval, with the row's trial
or pair count (the first of ``COUNTS`` present) as the denominator. One line
per file: rows joined, rate cells, cells identical, cells outside the
interval, and the largest difference. The interval is the new run's own
sampling error; the same seeds make the two runs paired, so on identical
code every cell is identical and a last-bit change moves only a few trials.

Per-found rates (denominator: the found pairs, not the row's count) are
judged against the row's count too, which makes their interval too narrow;
a cell outside it is listed so that it can be looked at.
"""

from __future__ import annotations

import argparse
import io
import re
import subprocess
import sys

import numpy as np
import pandas as pd

from experiments.intervals import wilson

#: Columns that name a configuration (joined on) rather than a measurement.
KEYS = ("kind", "cut", "source", "n_landmarks", "overlap", "snr_db", "SNR", "aspect", "unrelated", "layout",
        "p_detect", "clutter", "anisotropy", "method", "objective", "use_cov", "tau", "maximiser", "peer",
        "n_agents", "topology", "n_strangers", "until_s", "robot", "robots", "pairs_kind", "bend_deg",
        "false_alarm", "benchmark", "launcher")
#: Rate columns: proportions of the row's trials or pairs.
RATE = re.compile(r"(rate|^p_d$|^p_fa$|^precision$|^recall|found$|^success$)")
#: The denominators, in order of preference.
COUNTS = ("n_trials", "related_pairs", "pairs", "n_pairs", "trials", "teams")


def compare(old: pd.DataFrame, new: pd.DataFrame) -> dict:
    """Rate cells of two versions of one table, joined on their shared configuration columns."""
    keys = [k for k in KEYS if k in old.columns and k in new.columns]
    count = next((c for c in COUNTS if c in new.columns), None)
    rates = [c for c in new.columns if c in old.columns and c not in keys and RATE.search(c)
             and pd.api.types.is_numeric_dtype(new[c]) and new[c].between(0, 1).all()]
    out = {"rows": 0, "cells": 0, "identical": 0, "outside": 0, "max_diff": 0.0, "worst": ""}
    if not keys or count is None or not rates:
        return out
    joined = old[keys + rates].merge(new[keys + rates + [count]], on=keys, suffixes=("_old", "_new"))
    out["rows"] = len(joined)
    n = joined[count].to_numpy(float)
    for c in rates:
        a, b = joined[f"{c}_old"].to_numpy(float), joined[f"{c}_new"].to_numpy(float)
        ok = np.isfinite(a) & np.isfinite(b) & (n > 0)
        lo, hi = wilson(b[ok] * n[ok], n[ok])
        outside = (a[ok] < lo - 1e-12) | (a[ok] > hi + 1e-12)
        out["cells"] += int(ok.sum())
        out["identical"] += int(np.sum(a[ok] == b[ok]))
        out["outside"] += int(outside.sum())
        if ok.any() and np.max(np.abs(a[ok] - b[ok])) > out["max_diff"]:
            i = int(np.argmax(np.abs(a[ok] - b[ok])))
            out["max_diff"] = float(abs(a[ok][i] - b[ok][i]))
            row = joined[ok].iloc[i]
            out["worst"] = f"{c} {a[ok][i]:.4g} -> {b[ok][i]:.4g} (n {n[ok][i]:.0f}; " + \
                ", ".join(f"{k}={row[k]}" for k in keys if row[k] == row[k]) + ")"
    return out


def changed_csvs(base: str, paths: list[str]) -> list[str]:
    """Tracked CSV files under paths that differ from their version at base."""
    names = subprocess.run(["git", "diff", "--name-only", base, "--", *paths], check=True,
                           capture_output=True, text=True).stdout.split()
    return [p for p in names if p.endswith(".csv")]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="HEAD", help="the revision to compare with (default HEAD)")
    parser.add_argument("paths", nargs="*", default=["results"])
    args = parser.parse_args(argv)
    for path in changed_csvs(args.base, args.paths):
        try:
            old_text = subprocess.run(["git", "show", f"{args.base}:{path}"], check=True,
                                      capture_output=True, text=True).stdout
        except subprocess.CalledProcessError:
            print(f"{path}: new file")
            continue
        r = compare(pd.read_csv(io.StringIO(old_text)), pd.read_csv(path))
        if not r["cells"]:
            print(f"{path}: no rate columns to compare")
            continue
        print(f"{path}: {r['rows']} rows, {r['cells']} rate cells, {r['identical']} identical, "
              f"{r['outside']} outside the new 95 % interval; largest difference {r['max_diff']:.4g}"
              + (f": {r['worst']}" if r["max_diff"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
