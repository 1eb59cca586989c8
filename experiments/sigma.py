"""How merges depend on a wrong σ (results/sigma/table.md).

    python -m experiments.sigma            # about a minute

``merge_maps`` is told ``factor · σ`` instead of the true σ on the paper's
100-landmark scenario (75 % common), 100 related and 100 unrelated pairs per
SNR, seeds 0-99 (related) and 1000-1099 (unrelated). Reported per method,
SNR and factor: merge success (rotation error < 1°, RMSE < 2σ), correct and
wrong landmark pairs per trial, and false merges on the unrelated pairs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

import mapmerge as mm

from .aggregate import save_table

FACTORS = (0.25, 0.5, 1.0, 2.0, 4.0)
SNRS = (20.0, 30.0)


def measure(n_trials: int = 100, methods=("consensus", "paper")) -> pd.DataFrame:
    rows = []
    for snr in SNRS:
        related = mm.simulate.make_pairs(100, 0.75, snr, list(range(n_trials)))
        unrelated = mm.simulate.make_pairs(100, 0.75, snr, list(range(1000, 1000 + n_trials)), unrelated=True)
        for method in methods:
            for factor in FACTORS:
                merged = mm.merge_batch(related.p, related.q, factor * related.sigma, method=method)
                err = mm.metrics.map_errors_batch(related, merged)
                false = mm.merge_batch(unrelated.p, unrelated.q, factor * unrelated.sigma, method=method).matched
                rows.append({"method": method, "snr_db": snr, "sigma_factor": factor,
                             "success_rate": err["success"].mean(),
                             "correct_pairs": err["correct_pairs"].mean(), "wrong_pairs": err["wrong_pairs"].mean(),
                             "false_merges": f"{int(false.sum())} / {n_trials}"})
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Merge quality when merge_maps is told a wrong sigma.")
    parser.add_argument("--out", default="results/sigma")
    parser.add_argument("--trials", type=int, default=100)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path in save_table(measure(args.trials), out / "table"):
        print(path)
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()
