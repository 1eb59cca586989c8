"""The outside peers (CPD, CLIPPER, TEASER++) against our methods on the same map pairs (results/peers/).

    python -m experiments.peers [--out results/peers]          # the comparison, then its tables
    python -m experiments.peers --calibrate [--out results/peers]   # the peers' acceptance thresholds

Every method sees the same pairs: ``make_pair(n, 0.75, snr, rng=seed)``
(strip layout) with seeds 0, 1, ... for the related pairs and the same seeds
with ``unrelated=True`` for the unrelated ones, at n = 10 and 20 landmarks
(15, 20, 30 dB) and n = 100 (10, 15, 20, 30 dB). Methods: consensus, the
paper, Groth's voting, astroalign (when installed) and the peers that are
installed (``pip install 'mapmerge[peers]'``; ``tools/build_peers.sh``).
``PAIRS`` related and as many unrelated pairs per cell, fewer for the slow
ones (``SLOW_PAIRS``). Writes ``peers.csv`` / ``peers.md``: transform found
(``metrics.transform_found``'s rule) with its 95 % Wilson interval, false
merges on the unrelated pairs, the median seconds per merge (one pair at a
time, on the first ``TIMED_PAIRS`` related pairs), and beside them two
limits: the fit knowing every correspondence
(``metrics.correspondence_oracle_transform``) on the same pairs, and the
exhaustive ML detector's found rate where results/detector/ has the cell
(its own pairs and threshold; see that directory).

``--calibrate`` draws ``CALIBRATION_PAIRS`` unrelated pairs at 30 dB per map
size from seeds ``CALIBRATION_SEED`` + i (disjoint from the reported ones),
records each peer's inlier count before its acceptance test and writes
``calibration.csv`` / ``.md``: per peer and size, the largest and second
largest inlier share of the smaller map, and the smallest acceptance share
that lets at most one of them through. The peers' module constants
(``*_MIN_INLIERS``) hold, per size, the least inlier count that lets at most one through.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import time
from multiprocessing import Pool
from pathlib import Path

# CLIPPER and TEASER++ use OpenMP; the two worker processes are the parallelism.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pandas as pd

import mapmerge as mm
from experiments.intervals import wilson
from mapmerge.baselines import clipper, cpd, teaser

#: (landmarks per map, SNR in dB) of every cell; overlap 0.75, strip layout.
CELLS = [(10, 15), (10, 20), (10, 30), (20, 15), (20, 20), (20, 30), (100, 10), (100, 15), (100, 20), (100, 30)]
OVERLAP = 0.75
#: Related (and as many unrelated) pairs per cell.
PAIRS = 200
#: Fewer pairs for methods slow at a map size: (method, n) -> pairs (0: not run).
#: astroalign is not run at 100 landmarks: 0.35-5 s per merge there (results/compare).
SLOW_PAIRS = {("cpd", 100): 25, ("astroalign", 100): 0}
#: Related pairs timed one at a time per cell.
TIMED_PAIRS = 10
#: Unrelated calibration pairs per map size at 30 dB, and their first seed (reported seeds start at 0).
CALIBRATION_PAIRS = {10: 1000, 20: 1000, 100: 1000}
SLOW_CALIBRATION_PAIRS = {("cpd", 100): 200}
CALIBRATION_SEED = 10**6
CALIBRATION_SNR = 30.0
#: The peers' inlier sets before acceptance (pair -> (K, 2) pairs).
PEER_PAIRS = {
    "cpd": lambda sc: cpd.cpd_pairs(sc.p, sc.q, sc.sigma),
    "clipper": lambda sc: clipper.clipper_pairs(sc.p, sc.q, sc.sigma),
    "teaser": lambda sc: teaser.teaser_pairs(sc.p, sc.q, sc.sigma),
}
PEER_MODULES = {"cpd": "pycpd", "clipper": "clipperpy", "teaser": "teaserpp_python", "astroalign": "astroalign"}


def available_methods() -> list[str]:
    """consensus, paper, groth, then every optional method whose package is importable."""
    optional = [m for m in ("astroalign", "cpd", "clipper", "teaser") if importlib.util.find_spec(PEER_MODULES[m])]
    return ["consensus", "paper", "groth", *optional]


def run_cell(job) -> dict:
    """One method on one cell: found, false merges, time."""
    method, n, snr = job
    count = SLOW_PAIRS.get((method, n), PAIRS)
    seeds = list(range(count))
    out = {"method": method, "n_landmarks": n, "snr_db": snr, "pairs": count}
    for unrelated in (False, True):
        scen = mm.simulate.make_pairs(n, OVERLAP, snr, seeds, unrelated=unrelated)
        merged = mm.merge_batch(scen.p, scen.q, scen.sigma, method=method, rng=0)
        err = mm.metrics.map_errors_batch(scen, merged)
        if unrelated:
            out["false_merges"] = int(err["false_merge"].sum())
        else:
            out["found"] = int(err["transform_found"].sum())
    times = []
    for seed in range(TIMED_PAIRS):
        sc = mm.simulate.make_pair(n, OVERLAP, snr, rng=seed)
        t0 = time.perf_counter()
        mm.merge_maps(sc.p, sc.q, sc.sigma, method=method, rng=0)
        times.append(time.perf_counter() - t0)
    out["median_s"] = float(np.median(times))
    return out


def oracle_found(n: int, snr: float) -> int:
    """Related pairs of a cell whose fit knowing every correspondence counts as found."""
    hits = 0
    for seed in range(PAIRS):
        sc = mm.simulate.make_pair(n, OVERLAP, snr, rng=seed)
        fit = mm.metrics.correspondence_oracle_transform(sc)
        hits += mm.metrics.transform_found(sc, fit.theta, fit.t)
    return hits


def detector_limits() -> pd.DataFrame:
    """The exhaustive detector's found rate per (n, SNR) from results/detector/ (strip layout), if present."""
    frames = [pd.read_csv(p) for p in (Path("results/detector/limit.csv"), Path("results/detector/small/limit.csv"))
              if p.exists()]
    if not frames:
        return pd.DataFrame(columns=["n_landmarks", "snr_db", "detector_found", "detector_null_pairs"])
    lim = pd.concat(frames)
    lim = lim[lim["layout"] == "strip"]
    return lim.rename(columns={"found_rate": "detector_found", "null_pairs": "detector_null_pairs"})[
        ["n_landmarks", "snr_db", "detector_found", "detector_null_pairs"]]


def compare(out: Path, processes: int = 2) -> pd.DataFrame:
    """Every available method on every cell; writes peers.csv / peers.md."""
    methods = available_methods()
    jobs = [(m, n, snr) for n, snr in CELLS for m in methods if SLOW_PAIRS.get((m, n), PAIRS)]
    # Slowest first so that the two workers finish together.
    jobs.sort(key=lambda j: -SLOW_PAIRS.get((j[0], j[1]), PAIRS) * j[1] ** 2)
    rows = []
    with Pool(processes) as pool:
        for row in pool.imap_unordered(run_cell, jobs):
            rows.append(row)
            print(f"{len(rows)}/{len(jobs)} {row}", flush=True)
        oracle = dict(zip(CELLS, pool.starmap(oracle_found, CELLS)))
    df = pd.DataFrame(rows)
    # Methods left out of a cell (SLOW_PAIRS 0) get an empty row, so that the table says so.
    ran = set(zip(df["method"], df["n_landmarks"], df["snr_db"]))
    df = pd.concat([df, pd.DataFrame([{"method": m, "n_landmarks": n, "snr_db": snr, "pairs": 0}
                                      for n, snr in CELLS for m in methods if (m, n, snr) not in ran])],
                   ignore_index=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        lo, hi = wilson(df["found"].to_numpy(), df["pairs"].to_numpy())
    df["found_rate"] = df["found"] / df["pairs"]
    df["found_lo"], df["found_hi"] = lo, hi
    df["correspondence_oracle_found"] = [oracle[(n, s)] / PAIRS for n, s in zip(df["n_landmarks"], df["snr_db"])]
    df["snr_db"] = df["snr_db"].astype(float)
    df = df.merge(detector_limits(), on=["n_landmarks", "snr_db"], how="left")
    df["method"] = pd.Categorical(df["method"], methods)
    df = df.sort_values(["n_landmarks", "snr_db", "method"]).reset_index(drop=True)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "peers.csv", index=False, float_format="%.4g")
    write_markdown(df, out / "peers.md")
    return df


def write_markdown(df: pd.DataFrame, path: Path) -> None:
    """peers.md: one row per (n, SNR), one column per method (found rate [interval], false merges, time)."""
    methods = list(df["method"].cat.categories)
    lines = [("Transform found on related pairs, % [95 % Wilson interval] (pairs), false merges on as many "
              "unrelated pairs, median seconds per merge. Limits: the fit knowing every correspondence on the "
              "same pairs; the exhaustive detector (results/detector/, its own pairs and threshold)."), "",
             "| n, SNR | " + " | ".join(methods) + " | oracle fit | detector |",
             "|---|" + "---|" * (len(methods) + 2)]
    for (n, snr), cell in df.groupby(["n_landmarks", "snr_db"], sort=True):
        by = cell.set_index("method", drop=False)
        parts = []
        for m in methods:
            if m not in by.index or pd.isna(by.loc[m, "found"]):
                parts.append("not run")
                continue
            r = by.loc[m]
            parts.append(f"{100 * r.found_rate:.0f} [{100 * r.found_lo:.0f}, {100 * r.found_hi:.0f}] ({int(r.pairs)}), "
                         f"{int(r.false_merges)} false, {r.median_s:.3g} s")
        first = cell.iloc[0]
        det = "" if pd.isna(first.detector_found) else f"{100 * first.detector_found:.0f}"
        lines.append(f"| {n}, {snr:g} dB | " + " | ".join(parts) +
                     f" | {100 * first.correspondence_oracle_found:.0f} | {det} |")
    path.write_text("\n".join(lines) + "\n")


def calibration_scores(job) -> dict:
    """A peer's inlier shares on a map size's unrelated calibration pairs at 30 dB."""
    peer, n = job
    count = SLOW_CALIBRATION_PAIRS.get((peer, n), CALIBRATION_PAIRS[n])
    shares = np.array([len(PEER_PAIRS[peer](mm.simulate.make_pair(n, OVERLAP, CALIBRATION_SNR,
                                                                  rng=CALIBRATION_SEED + i, unrelated=True))) / n
                       for i in range(count)])
    top = np.sort(shares)[::-1]
    # At most one pair may reach the threshold: just above the second-largest share (counts are integers).
    need = (np.round(top[1] * n) + 1) / n
    return {"peer": peer, "n_landmarks": n, "pairs": count, "max_share": top[0], "second_share": top[1],
            "threshold_share": need}


def calibrate(out: Path, processes: int = 2) -> pd.DataFrame:
    """The peers' acceptance thresholds (see the module docstring); writes calibration.csv / .md."""
    peers = [p for p in PEER_PAIRS if importlib.util.find_spec(PEER_MODULES[p])]
    jobs = [(p, n) for p in peers for n in CALIBRATION_PAIRS]
    jobs.sort(key=lambda j: -j[1])
    with Pool(processes) as pool:
        df = pd.DataFrame(pool.map(calibration_scores, jobs, chunksize=1))
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "calibration.csv", index=False, float_format="%.4g")
    (out / "calibration.md").write_text(df.to_markdown(index=False, floatfmt=".3g") + "\n")
    return df


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("results/peers"))
    ap.add_argument("--calibrate", action="store_true", help="set the peers' thresholds instead")
    ap.add_argument("--processes", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    df = (calibrate if args.calibrate else compare)(args.out, args.processes)
    print(df.to_string())
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
