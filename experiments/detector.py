"""The exhaustive ML detector's limit curve: could any matcher have merged these pairs? (results/detector/)

    python -m experiments.detector                  # 100 pairs per cell, 0-12.5 dB, both layouts
    python -m experiments.detector --trials 20      # a quick look

Per layout (strip; interleaved with p_detect 0.9) and SNR, on the paper's
Fig. 1 scenario (100 landmarks per map, 75 % common):

1. the null: ``mapmerge.exhaustive.max_log_lr`` on unrelated pairs of the
   tuning seeds 300000+k. The statistic is a maximum, so its upper tail is
   exponential (Gumbel's domain of attraction): above the null's
   ``TAIL_QUANTILE`` quantile u, the exceedances are fitted with an
   exponential law of mean β, and the threshold at a false-alarm rate
   ``FALSE_ALARM`` per pair is ``u + β log((1 - TAIL_QUANTILE) / FALSE_ALARM)``
   (peaks over threshold);
2. related pairs on seeds 100000+k (disjoint from the tuning seeds): the
   detector merges when the statistic passes the threshold, and the pair
   counts as found when it also put the transform within 1° and σ
   (``mapmerge.metrics.transform_found``).

The detector knows the true σ and the layout's prior, so it is a limit (an
oracle), not a method. Above 12.5 dB every pair is far above the null (see
the table's margins), and the matchers merge there too.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

import mapmerge as mm
from mapmerge.consensus import SHARED_RANGE

from .aggregate import save_table

SNRS = np.arange(0.0, 12.51, 2.5)
LAYOUTS = ("strip", "interleaved")
#: False alarms per unrelated pair allowed to the detector, as for the matchers' targets.
FALSE_ALARM = 1e-3
#: The null's exponential tail is fitted above this quantile.
TAIL_QUANTILE = 0.75
TUNING_SEED, REPORTED_SEED = 300_000, 100_000


def statistic(layout: str, snr: float, seed: int, unrelated: bool) -> tuple[float, bool, float]:
    """(max Λ, transform found, seconds) of one pair."""
    sc = mm.simulate.make_pair(100, 0.75, snr, rng=seed, unrelated=unrelated, layout=layout)
    clock = time.perf_counter()
    value, theta, t = mm.exhaustive.max_log_lr(sc.p, sc.q, sc.sigma, float(np.clip(sc.p_shared, *SHARED_RANGE)),
                                               sc.density)
    seconds = time.perf_counter() - clock
    return value, (not unrelated) and mm.metrics.transform_found(sc, theta, t), seconds


def null_threshold(null: np.ndarray) -> float:
    """Threshold at ``FALSE_ALARM`` from null statistics: an exponential tail above their ``TAIL_QUANTILE``."""
    u = float(np.quantile(null, TAIL_QUANTILE))
    beta = float(np.mean(null[null > u] - u))
    return u + beta * np.log((1 - TAIL_QUANTILE) / FALSE_ALARM)


def run_pairs(trials: int, n_jobs: int) -> pd.DataFrame:
    """The statistic of every null and related pair: one row each."""
    jobs = [(layout, float(snr), int(seed), unrelated) for layout in LAYOUTS for snr in SNRS
            for unrelated, base in ((True, TUNING_SEED), (False, REPORTED_SEED)) for seed in base + np.arange(trials)]
    out = Parallel(n_jobs=n_jobs, batch_size=4)(delayed(statistic)(*job) for job in jobs)
    return pd.DataFrame([(*job, *res) for job, res in zip(jobs, out)],
                        columns=["layout", "snr_db", "seed", "unrelated", "log_lr", "found", "seconds"])


def limit_table(runs: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for (layout, snr), g in runs.groupby(["layout", "snr_db"], sort=False):
        null, related = g[g.unrelated].log_lr.to_numpy(), g[~g.unrelated]
        threshold = null_threshold(null)
        detected = related.log_lr.to_numpy() >= threshold
        rows.append({"layout": layout, "snr_db": snr, "null_pairs": len(null), "null_max": null.max(),
                     "threshold": threshold, "related_pairs": len(related),
                     "detected_rate": detected.mean(), "found_rate": (detected & related.found.to_numpy()).mean(),
                     "median_related_log_lr": float(np.median(related.log_lr)),
                     "median_s": float(np.median(g.seconds))})
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="The exhaustive ML detector's limit curve.")
    parser.add_argument("--trials", type=int, default=100, help="pairs per cell, null and related each")
    parser.add_argument("--out", default="results/detector")
    parser.add_argument("--n-jobs", type=int, default=2)
    parser.add_argument("--tables", action="store_true", help="only rebuild limit.* from the saved pairs.csv")
    args = parser.parse_args(argv)
    if args.trials < 8:
        raise SystemExit("--trials must be >= 8 (the null's tail fit needs them)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.tables:
        runs = pd.read_csv(out / "pairs.csv")
    else:
        runs = run_pairs(args.trials, args.n_jobs)
        runs.to_csv(out / "pairs.csv", index=False, float_format="%.10g")  # seconds: the one machine-dependent column
    for path in save_table(limit_table(runs), out / "limit"):
        print(path)


if __name__ == "__main__":
    main()
