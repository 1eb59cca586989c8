"""Consensus at low SNR against the exhaustive detector's limit (results/low_snr/).

    python -m experiments.low_snr            # the low_snr preset, then the summary
    python -m experiments.low_snr --tables   # only rebuild the summary from results/low_snr

Runs the ``low_snr`` sweep (consensus, which falls back to the global search
when its triangles find nothing, on the paper's Fig. 1 scenario: 100
landmarks per map, 75 % common, strip and interleaved layouts, 0-40 dB in
2.5 dB steps, 1,000 related and 1,000 unrelated pairs per cell) and writes

* ``summary.md`` / ``.csv``: per layout and SNR, transform found (rotation
  within 1° and registration RMS within σ) with its 95 % Wilson interval,
  false merges on the unrelated pairs and the median time per merge;
* ``crossing.md`` / ``.csv``: per layout, the SNR at which consensus and
  the exhaustive ML detector (``results/detector/limit.csv``, ``python -m
  experiments.detector``) first find 90 % of the transforms, interpolated
  linearly between grid SNRs, and their difference.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import norm

from .aggregate import save_table, with_timing
from .paper import _call

#: The success rate whose SNR is compared with the detector's.
LEVEL = 0.9


def wilson(successes: np.ndarray, n: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval of a binomial proportion."""
    z = norm.ppf(0.5 + level / 2)
    p = successes / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    return centre - half, centre + half


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Related cells with their unrelated twins' false merges."""
    keys = ["layout", "snr_db"]
    related = table[~table.unrelated.astype(bool)].copy()
    unrelated = table[table.unrelated.astype(bool)].assign(
        false_merges=lambda t: (t.false_merge_rate * t.n_trials).round().astype(int))
    low, high = wilson(np.round(related.found_rate * related.n_trials), related.n_trials.to_numpy())
    related["found_low"], related["found_high"] = low, high
    out = related.merge(unrelated[keys + ["false_merges", "n_trials"]], on=keys, suffixes=("", "_unrelated"))
    names = {"layout": "layout", "snr_db": "SNR", "n_trials": "pairs", "found_rate": "transform found",
             "found_low": "95 % low", "found_high": "95 % high", "false_merges": "false merges",
             "n_trials_unrelated": "unrelated pairs", "median_ms_per_merge": "median ms"}
    return out.sort_values(keys)[list(names)].rename(columns=names)


def crossing_snr(snr: np.ndarray, rate: np.ndarray, level: float = LEVEL) -> float:
    """First SNR where ``rate`` reaches ``level``, linear between grid points (nan if never)."""
    above = np.flatnonzero(rate >= level)
    if not len(above):
        return float("nan")
    k = above[0]
    if k == 0:
        return float(snr[0])
    return float(snr[k - 1] + (level - rate[k - 1]) * (snr[k] - snr[k - 1]) / (rate[k] - rate[k - 1]))


def crossing(found: pd.DataFrame, limit: pd.DataFrame) -> pd.DataFrame:
    """Per layout: the SNR at ``LEVEL`` transform found for consensus and the detector."""
    rows = []
    for layout, g in found.groupby("layout", sort=False):
        g = g.sort_values("SNR")
        d = limit[limit.layout == layout].sort_values("snr_db")
        ours = crossing_snr(g.SNR.to_numpy(), g["transform found"].to_numpy())
        det = crossing_snr(d.snr_db.to_numpy(), d.found_rate.to_numpy())
        rows.append({"layout": layout, "level": LEVEL, "consensus SNR": ours, "detector SNR": det,
                     "behind detector (dB)": ours - det})
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Consensus at low SNR against the exhaustive detector.")
    parser.add_argument("--out", default="results/low_snr")
    parser.add_argument("--limit", default="results/detector/limit.csv", help="the detector's table")
    parser.add_argument("--tables", action="store_true", help="only rebuild the summary")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides")
    args = parser.parse_args(argv)
    out = Path(args.out)
    if not args.tables:
        _call(["experiments.run", "-m", "experiment=low_snr", f"aggregate_dir={out}", "mc.progress=false",
               *args.overrides])
    found = summary(with_timing(out / "table.csv"))
    paths = save_table(found, out / "summary")
    if Path(args.limit).exists():
        paths += save_table(crossing(found, pd.read_csv(args.limit)), out / "crossing")
    for path in paths:
        print(path)


if __name__ == "__main__":
    main()
