"""Transform found vs SNR for the global search and consensus (results/search/).

    python -m experiments.search_curve                 # 200 trials per SNR, 0-40 dB in 2.5 dB steps
    python -m experiments.search_curve --trials 20     # a quick look

On the paper's Fig. 1 scenario (100 landmarks per map, 75 % common, strip
layout), per method and SNR: the fraction of related pairs whose transform
was found (rotation within 1° and RMS registration error over the common
landmarks, estimated vs true transform applied to the same points, within
σ), false merges on as many unrelated pairs, and the median time per merge.
Trial seeds 100000+k (related) and 200000+k (unrelated) are disjoint from
the seeds the search's constants were chosen on (10000-10019).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

import mapmerge as mm

from .aggregate import save_table

SNRS = np.arange(0.0, 40.01, 2.5)


def cell(method: str, snr: float, trials: int) -> dict:
    found = false = 0
    times = []
    for k in range(trials):
        sc = mm.simulate.make_pair(100, 0.75, snr, rng=100_000 + k)
        clock = time.perf_counter()
        res = mm.merge_maps(sc.p, sc.q, sc.sigma, method=method)
        times.append(time.perf_counter() - clock)
        found += res.matched and mm.metrics.transform_found(sc, res.theta, res.t)
        un = mm.simulate.make_pair(100, 0.75, snr, rng=200_000 + k, unrelated=True)
        false += mm.merge_maps(un.p, un.q, un.sigma, method=method).matched
    return {"method": method, "snr_db": snr, "trials": trials, "transform_found": found / trials,
            "false_merges": false, "median_ms": 1e3 * float(np.median(times))}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Transform found vs SNR: global search and consensus.")
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--methods", default="consensus,search")
    parser.add_argument("--out", default="results/search")
    parser.add_argument("--n-jobs", type=int, default=2)
    args = parser.parse_args(argv)
    if args.trials < 1:
        raise SystemExit("--trials must be >= 1")
    jobs = [(m, float(s)) for m in args.methods.split(",") for s in SNRS]
    rows = Parallel(n_jobs=args.n_jobs)(delayed(cell)(m, s, args.trials) for m, s in jobs)
    table = pd.DataFrame(rows).sort_values(["method", "snr_db"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path in save_table(table, out / "found"):
        print(path)


if __name__ == "__main__":
    main()
