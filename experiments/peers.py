"""The outside peers (CPD, CLIPPER, TEASER++) against our methods on the same map pairs (results/peers/).

    python -m experiments.peers [--layout strip|interleaved] [--methods M ...] [--processes 1]
    python -m experiments.peers --scaling [--sizes 100 1000 10000] [--time-limit 120]   # time per merge
    python -m experiments.peers --calibrate [--methods M ...] [--out results/peers]   # acceptance thresholds
    python -m experiments.peers --equal-rate [--pairs 1000]   # every method at one false-merge rate per cell
    python -m experiments.peers --one-bound [--landmarks 10 20]   # each peer with one bound per map size

Every method sees the same pairs: ``make_pair(n, 0.75, snr, rng=seed,
layout=layout)`` with seeds 0, 1, ... for the related pairs and the same
seeds with ``unrelated=True`` for the unrelated ones. Strip layout: n = 10
and 20 landmarks (15, 20, 30 dB) and n = 100 (0, 5, 10, 15, 20, 30 dB);
interleaved layout: n = 10 and 20 (20, 30 dB) and n = 100 (0, 5, 10, 15,
20, 30 dB). Methods: consensus, the paper, Groth's voting, astroalign (when
installed) and the peers that are installed (``pip install
'mapmerge[peers]'``; ``tools/build_peers.sh``), or those named by
``--methods``. ``PAIRS`` related and as many unrelated pairs per cell, fewer
for the slow ones (``SLOW_PAIRS``). A run computes one layout's cells and
replaces that layout's rows of ``peers.csv``, keeping the other layout's;
``peers.md`` is rewritten from all of them. ``peers.csv`` holds: transform found
(``metrics.transform_found``'s rule) with its 95 % Wilson interval, wrong
merges (related pairs merged with a transform that is not found), false
merges on the unrelated pairs, the landmark pairs of the related pairs'
merges against the oracle association (each map pair's true common
landmarks: correct, wrong, and the common ones, summed over the cell), the
median seconds per merge (one pair at a time, on the first ``TIMED_PAIRS``
related pairs), and beside them two
limits: the fit knowing every correspondence
(``metrics.correspondence_oracle_transform``) on the same pairs, and the
exhaustive ML detector's found rate where results/detector/ has the cell
(its own pairs and threshold; see that directory). Each cell's row is kept
in ``CELL_ROWS`` as soon as it is done (keyed as ``--equal-rate``'s chunks
are, below), so a stopped run resumes.

``--scaling`` times one merge at a time on the first ``SCALING_PAIRS``
related pairs at 30 dB (strip layout) of ``SCALING_SIZES`` landmarks, for
consensus and the installed peers. Each merge runs in a child process
that is stopped past ``--time-limit`` seconds or when it needs more than
``SCALING_MEMORY_GB`` of memory; after such a stop the method is not run at
that size's remaining pairs nor at larger sizes. Writes ``scaling.csv`` /
``scaling.md``.

``--calibrate`` draws ``CALIBRATION_PAIRS`` unrelated pairs at 30 dB per map
size from seeds ``CALIBRATION_SEED`` + i (disjoint from the reported ones),
records each peer's inlier count before its acceptance test and writes
``calibration.csv`` / ``.md``: per peer and size, the largest and second
largest inlier share of the smaller map, and the smallest acceptance share
that lets at most one of them through (each peer and size kept in
``CELL_ROWS`` as soon as it is done). The peers' module constants
(``*_MIN_INLIERS``) hold, per size, the least inlier count that lets at most one through.

``--equal-rate`` compares the methods at one false-merge rate in every
cell (``EQUAL_RATE_CELLS``), not only at the 30 dB the shipped bounds were
set at: below it a peer's chance inliers grow and its shipped bound lets
most unrelated pairs through. Per cell, each peer's inliers are counted on
``EQUAL_RATE_TUNING`` unrelated tuning pairs of that cell (seeds
``CALIBRATION_SEED`` + i), and its bound is the least count that lets at
most a share ``EQUAL_RATE`` of them through; on the cell's reported pairs
(seeds 0, 1, ...: related and as many unrelated) it then accepts a merge
when its inliers reach that bound. ``consensus`` keeps its own a contrario
test. Each chunk of pairs is kept in ``EQUAL_RATE_ROWS`` (keyed by the
digest of the library sources the method runs and of the code that
computes a chunk) as soon as it is done, so a stopped run resumes. Writes
``equal_rate.csv`` / ``.md`` and the figure ``equal_rate.png`` / ``.pdf``.

``--one-bound`` holds each installed peer to ``consensus_count``'s rule
instead: one bound per map size, whatever the SNR and layout. On the
small-map cells ``ONE_BOUND_CELLS`` (10 dB included, as for the count
levels) it counts inliers on the same tuning, related and unrelated pairs
as ``--equal-rate`` (its chunks, shared), sets the bound of each cell as
there, and per size and floor of ``ONE_BOUND_FLOORS`` takes the largest
bound of the cells from that SNR up. Writes ``one_bound.csv`` / ``.md``:
found rate, wrong and false merges at that bound and at the cell's own,
keeping the rows of peers and sizes not run.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import importlib.util
import inspect
import itertools
import json
import os
import time
from multiprocessing import Pool
from pathlib import Path
from unittest import mock

# CLIPPER and TEASER++ use OpenMP; the two worker processes are the parallelism.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pandas as pd

import mapmerge as mm
from experiments.intervals import wilson
from mapmerge.baselines import clipper, cpd, teaser
from mapmerge.baselines.associations import min_inliers
from mapmerge.result import MIN_MATCHED_LANDMARKS

#: (landmarks per map, SNR in dB) of every cell per layout; overlap 0.75.
CELLS = {"strip": [(10, 15), (10, 20), (10, 30), (20, 15), (20, 20), (20, 30),
                   (100, 0), (100, 5), (100, 10), (100, 15), (100, 20), (100, 30)],
         "interleaved": [(10, 20), (10, 30), (20, 20), (20, 30),
                         (100, 0), (100, 5), (100, 10), (100, 15), (100, 20), (100, 30)]}
OVERLAP = 0.75
#: Related (and as many unrelated) pairs per cell.
PAIRS = 200
#: Fewer pairs for methods slow at a map size, or at a map size and SNR: (method, n) or (method, n, SNR) ->
#: pairs (0: not run; the SNR's entry first). astroalign is not run at 100 landmarks: 0.35-5 s per merge there
#: (results/compare). TEASER++ is not run at 100 landmarks and 0-5 dB: there most putative associations are
#: mutually consistent (a dense graph), and its exact maximum clique took 1.5-4 s on three pairs at 5 dB,
#: 30-40 s on two at 0 dB, and a run of 50 pairs at 5 dB and 10 at 0 dB was stopped after 30 minutes.
SLOW_PAIRS = {("cpd", 100): 25, ("astroalign", 100): 0, ("teaser", 100, 5): 0, ("teaser", 100, 0): 0}
#: Where ``compare`` and ``--calibrate`` keep each cell's row (not committed), keyed like ``--equal-rate``'s
#: chunks.
CELL_ROWS = Path("outputs") / "peers" / "cells"
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
#: Time per merge: map sizes, related pairs per size (30 dB, strip layout), child memory cap.
SCALING_SIZES = (100, 1000, 10000)
SCALING_PAIRS = 3
SCALING_SNR = 30.0
SCALING_MEMORY_GB = 8
PEER_MODULES = {"cpd": "pycpd", "clipper": "clipperpy", "teaser": "teaserpp_python", "astroalign": "astroalign"}
#: Each peer's module and the name of its table of acceptance bounds (``--equal-rate`` sets them per cell).
PEER_BOUNDS = {"cpd": (cpd, "CPD_MIN_INLIERS"), "clipper": (clipper, "CLIPPER_MIN_INLIERS"),
               "teaser": (teaser, "TEASER_MIN_INLIERS")}
#: ``--equal-rate``: (landmarks per map, SNR in dB) of every cell, per layout.
EQUAL_RATE_CELLS = {layout: [(n, snr) for n in (10, 20) for snr in (15, 20, 25, 30, 35, 40)] +
                    [(100, snr) for snr in (0, 5, 10, 15, 20, 25, 30, 35, 40)] for layout in ("strip", "interleaved")}
#: The false-merge rate every peer is held to in each cell, and the unrelated tuning pairs it is set on.
EQUAL_RATE = 1e-3
EQUAL_RATE_TUNING = 1000
#: Reported related (and as many unrelated) pairs per cell at most (``--pairs`` for fewer); fewer for the slow
#: ones (0: not run): CPD takes 0.1 s a merge at 10-20 landmarks and 0.6-1.2 s at 100, where its 1,000 tuning
#: pairs per cell alone would take hours; CLIPPER and TEASER++ take 0.05-0.7 s a merge at 100 landmarks, and
#: TEASER++ is not run at 0-5 dB (``SLOW_PAIRS``). Keys as ``SLOW_PAIRS``'.
EQUAL_RATE_PAIRS = 1000
EQUAL_RATE_SLOW = {("cpd", 10): 500, ("cpd", 20): 500, ("cpd", 100): 0, ("clipper", 100): 500, ("teaser", 100): 500,
                   ("teaser", 100, 0): 0, ("teaser", 100, 5): 0}
#: The reason the tables give for a method left out of a cell (``SLOW_PAIRS`` or ``EQUAL_RATE_SLOW`` 0).
NOT_RUN = {("astroalign", 100): "not run: 0.35-5 s a merge",
           ("teaser", 100): "not run: its exact maximum clique takes seconds to minutes a merge here",
           ("cpd", 100): "not run: 0.6-1.2 s a merge, about an hour for a cell's 3,000 merges"}
#: ``--one-bound``: the small-map cells (both layouts, 10 dB included) over which each peer gets one bound per
#: map size, as ``consensus_count`` has one level per size: the largest of its cell bounds at that size.
ONE_BOUND_CELLS = [(layout, n, snr) for layout in ("strip", "interleaved") for n in (10, 20)
                   for snr in (10, 15, 20, 25, 30, 35, 40)]
#: The lowest SNR (dB) each one bound must hold from: 10 dB, as the count levels, and 15 dB, from where the
#: found rates are compared (a user who knows no more than that of their maps).
ONE_BOUND_FLOORS = (10.0, 15.0)
#: Pairs per job of ``--equal-rate`` (its unit of parallelism and of resumption).
EQUAL_RATE_CHUNK = 100
#: Where ``--equal-rate`` keeps each chunk's per-pair outcomes (not committed).
EQUAL_RATE_ROWS = Path("outputs") / "peers" / "equal_rate"
#: The library's sources a peer's chunk runs (the pairs, the peers' merge, the fit on their inliers, the
#: metrics), which key its kept chunks, so that a change to consensus's own stages keeps them. A test traces
#: a peer's chunk and checks that it runs no other module; ``neighbours`` holds compiled helpers, which a
#: trace of Python calls cannot see.
PEER_SOURCES = ("__init__.py", "_validation.py", "alignment.py", "assignment.py", "baselines", "combining.py",
                "matching.py", "merging.py", "metrics.py", "neighbours.py", "result.py", "simulate.py",
                "triangles.py")
#: Of ``baselines``, the modules every peer runs; beside them a peer runs only its own module.
SHARED_BASELINE_SOURCES = ("__init__.py", "associations.py")


def library_sources() -> list[Path]:
    """Every source file of the library, relative to it, in a fixed order."""
    library = Path(mm.__file__).resolve().parent
    return [f.relative_to(library) for f in sorted(library.rglob("*.py"))]


def peer_sources(method: str) -> list[Path]:
    """The library files a peer's chunk runs, relative to the library (``PEER_SOURCES``, of ``baselines``
    only the shared modules and the peer's own)."""
    own = (*SHARED_BASELINE_SOURCES, f"{method}.py")
    return [f for f in library_sources()
            if f.parts[0] in PEER_SOURCES and (f.parts[0] != "baselines" or f.name in own)]


def available_methods() -> list[str]:
    """consensus, paper, groth, then every optional method whose package is importable."""
    optional = [m for m in ("astroalign", "cpd", "clipper", "teaser") if importlib.util.find_spec(PEER_MODULES[m])]
    return ["consensus", "paper", "groth", *optional]


def fewer_pairs(table: dict, method: str, n: int, snr, pairs: int) -> int:
    """The pairs a method gets in a cell: ``table``'s entry for (method, n, SNR), else for (method, n), at most
    ``pairs`` (``SLOW_PAIRS``, ``EQUAL_RATE_SLOW``)."""
    return min(table.get((method, n, snr), table.get((method, n), pairs)), pairs)


def not_run(method: str, n: int) -> str:
    """The table entry of a method left out of a cell of n-landmark maps."""
    return NOT_RUN.get((method, n), "not run")


def kept_row(path: Path, compute, job) -> dict:
    """``compute(job)``, a dict of numbers and strings, kept at ``path`` as soon as it is done (and read back
    from there)."""
    if path.is_file():
        return json.loads(path.read_text())
    row = compute(job)
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_suffix(".part")
    part.write_text(json.dumps(row))
    part.replace(path)  # a stopped run leaves no half-written row
    return row


def cell_path(job) -> Path:
    method, layout, n, snr, count = job
    key = _rows_key(method, (kept_row, measure_cell), (OVERLAP, TIMED_PAIRS))
    return CELL_ROWS / f"{method}_{layout}_{n}_{snr:g}_{count}_{key}.json"


def run_cell(job) -> dict:
    """``measure_cell``, kept in ``CELL_ROWS``."""
    return kept_row(cell_path(job), measure_cell, job)


def measure_cell(job) -> dict:
    """One method on one cell: found, wrong merges of related pairs, false merges, landmark pairs, time."""
    method, layout, n, snr, count = job
    seeds = list(range(count))
    out = {"method": method, "layout": layout, "n_landmarks": n, "snr_db": snr, "pairs": count}
    for unrelated in (False, True):
        scen = mm.simulate.make_pairs(n, OVERLAP, snr, seeds, unrelated=unrelated, layout=layout)
        merged = mm.merge_batch(scen.p, scen.q, scen.sigma, method=method, rng=0)
        err = mm.metrics.map_errors_batch(scen, merged)
        if unrelated:
            out["false_merges"] = int(err["false_merge"].sum())
        else:
            out["found"] = int(err["transform_found"].sum())
            # A related pair merged with a transform outside the found rule's tolerance is a wrong merge, not a
            # miss: a method that accepts loosely gains found pairs and wrong merges together.
            out["wrong_merges"] = int(np.sum(err["matched"] & ~err["transform_found"]))
            # Landmark pairs against the oracle association (the pairs' true common landmarks).
            out["correct_pairs"] = int(err["correct_pairs"].sum())
            out["wrong_pairs"] = int(err["wrong_pairs"].sum())
            out["common_pairs"] = int((err["correct_pairs"] + err["missed_pairs"]).sum())
    times = []
    for seed in range(TIMED_PAIRS):
        sc = mm.simulate.make_pair(n, OVERLAP, snr, rng=seed, layout=layout)
        t0 = time.perf_counter()
        mm.merge_maps(sc.p, sc.q, sc.sigma, method=method, rng=0)
        times.append(time.perf_counter() - t0)
    out["median_s"] = float(np.median(times))
    return out


def oracle_found(layout: str, n: int, snr: float, count: int) -> int:
    """Related pairs of a cell (the first ``count``) whose fit knowing every correspondence counts as found."""
    hits = 0
    for seed in range(count):
        sc = mm.simulate.make_pair(n, OVERLAP, snr, rng=seed, layout=layout)
        fit = mm.metrics.correspondence_oracle_transform(sc)
        hits += mm.metrics.transform_found(sc, fit.theta, fit.t)
    return hits


def detector_limits() -> pd.DataFrame:
    """The exhaustive detector's found rate per (layout, n, SNR) from results/detector/, if present."""
    cols = ["layout", "n_landmarks", "snr_db", "detector_found", "detector_null_pairs"]
    frames = [pd.read_csv(p) for p in (Path("results/detector/limit.csv"), Path("results/detector/small/limit.csv"))
              if p.exists()]
    if not frames:
        return pd.DataFrame(columns=cols)
    lim = pd.concat(frames)
    return lim.rename(columns={"found_rate": "detector_found", "null_pairs": "detector_null_pairs"})[cols]


def compare(out: Path, processes: int = 2, layout: str = "strip", methods=None, pairs: int = PAIRS) -> pd.DataFrame:
    """``methods`` (default: every available one) on a layout's cells; updates their rows of peers.csv and
    peers.md, keeping the other methods' rows."""
    if layout not in CELLS:
        raise ValueError(f"layout must be one of {list(CELLS)}, got {layout!r}")
    methods = list(methods or available_methods())
    cells = CELLS[layout]
    counts = {(m, n, snr): fewer_pairs(SLOW_PAIRS, m, n, snr, pairs) for m in methods for n, snr in cells}
    jobs = [(m, layout, n, snr, counts[m, n, snr]) for n, snr in cells for m in methods if counts[m, n, snr]]
    # Slowest first so that the workers finish together (large maps and low SNR are slow).
    jobs.sort(key=lambda j: -j[4] * j[2] ** 2 / (1 + j[3]))
    oracle_jobs = [(layout, n, snr, pairs) for n, snr in cells]
    rows = []
    if processes == 1:
        for row in map(run_cell, jobs):
            rows.append(row)
            print(f"{len(rows)}/{len(jobs)} {row}", flush=True)
        oracle = dict(zip(cells, (oracle_found(*j) for j in oracle_jobs)))
    else:
        with Pool(processes) as pool:
            for row in pool.imap_unordered(run_cell, jobs):
                rows.append(row)
                print(f"{len(rows)}/{len(jobs)} {row}", flush=True)
            oracle = dict(zip(cells, pool.starmap(oracle_found, oracle_jobs)))
    df = pd.DataFrame(rows)
    # Methods left out of a cell (SLOW_PAIRS 0) get an empty row, so that the table says so.
    ran = set(zip(df["method"], df["n_landmarks"], df["snr_db"]))
    df = pd.concat([df, pd.DataFrame([{"method": m, "layout": layout, "n_landmarks": n, "snr_db": snr, "pairs": 0}
                                      for n, snr in cells for m in methods if (m, n, snr) not in ran])],
                   ignore_index=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        lo, hi = wilson(df["found"].to_numpy(), df["pairs"].to_numpy())
    df["found_rate"] = df["found"] / df["pairs"]
    df["found_lo"], df["found_hi"] = lo, hi
    df["correspondence_oracle_found"] = [oracle[(n, s)] / pairs for n, s in zip(df["n_landmarks"], df["snr_db"])]
    df["oracle_pairs"] = pairs
    df["snr_db"] = df["snr_db"].astype(float)
    df = df.merge(detector_limits(), on=["layout", "n_landmarks", "snr_db"], how="left")
    out.mkdir(parents=True, exist_ok=True)
    df = pd.concat([kept_rows(out / "peers.csv", layout, methods), df], ignore_index=True)
    order = [m for m in available_methods() + sorted(set(df["method"])) if m in set(df["method"])]
    df["method"] = pd.Categorical(df["method"], list(dict.fromkeys(order)))
    df = df.sort_values(["layout", "n_landmarks", "snr_db", "method"]).reset_index(drop=True)
    df.to_csv(out / "peers.csv", index=False, float_format="%.4g")
    write_markdown(df, out / "peers.md")
    return df


def kept_rows(path: Path, layout: str, methods) -> pd.DataFrame:
    """The rows of an earlier peers.csv but those of ``methods`` on ``layout`` (rows without one: strip)."""
    if not path.exists():
        return pd.DataFrame()
    old = pd.read_csv(path)
    if "layout" not in old:
        old.insert(1, "layout", "strip")
    if "oracle_pairs" not in old:
        old["oracle_pairs"] = PAIRS
    return old[(old["layout"] != layout) | ~old["method"].isin(methods)]


def write_markdown(df: pd.DataFrame, path: Path) -> None:
    """peers.md: one row per (layout, n, SNR), one column per method (found rate [interval], false merges,
    time); then the landmark pairs against the oracle association in the same layout."""
    methods = list(df["method"].cat.categories)
    lines = [("Transform found on related pairs, % [95 % Wilson interval] (pairs), wrong merges (related pairs "
              "merged with a transform that is not found), false merges on as many unrelated pairs, median "
              "seconds per merge. Limits: the fit knowing every correspondence on the "
              "first (oracle pairs) related pairs; the exhaustive detector (results/detector/, its own pairs "
              "and threshold)."), "",
             "| layout, n, SNR | " + " | ".join(methods) + " | oracle fit | detector |",
             "|---|" + "---|" * (len(methods) + 2)]
    pair_lines = ["", ("Landmark pairs of the related pairs' merges against the oracle association (each map "
                       "pair's true common landmarks): correct pairs, % of the common ones, and wrong pairs per "
                       "related map pair (declared pairs whose landmarks are not the same, or not common)."), "",
                  "| layout, n, SNR | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for (layout, n, snr), cell in df.groupby(["layout", "n_landmarks", "snr_db"], sort=True, observed=True):
        by = cell.set_index("method", drop=False)
        parts, pair_parts = [], []
        for m in methods:
            if m not in by.index or pd.isna(by.loc[m, "found"]):
                parts.append(not_run(m, n))
                pair_parts.append(not_run(m, n))
                continue
            r = by.loc[m]
            wrong = "" if pd.isna(r.get("wrong_merges")) else f"{int(r.wrong_merges)} wrong, "
            parts.append(f"{100 * r.found_rate:.0f} [{100 * r.found_lo:.0f}, {100 * r.found_hi:.0f}] ({int(r.pairs)}), "
                         f"{wrong}{int(r.false_merges)} false, {r.median_s:.3g} s")
            pair_parts.append("not recorded" if pd.isna(r.get("correct_pairs")) else
                              f"{100 * r.correct_pairs / r.common_pairs:.0f} % correct, "
                              f"{r.wrong_pairs / r.pairs:.1f} wrong")
        first = cell.iloc[0]
        det = "" if pd.isna(first.detector_found) else f"{100 * first.detector_found:.0f}"
        lines.append(f"| {layout}, {n}, {snr:g} dB | " + " | ".join(parts) +
                     f" | {100 * first.correspondence_oracle_found:.0f} ({int(first.oracle_pairs)}) | {det} |")
        pair_lines.append(f"| {layout}, {n}, {snr:g} dB | " + " | ".join(pair_parts) + " |")
    lines += pair_lines
    path.write_text("\n".join(lines) + "\n")


def timed_merge(conn, method: str, n: int, seed: int) -> None:
    """Child process of ``scaling``: one merge, its seconds (or the error) sent back through ``conn``."""
    import resource

    cap = SCALING_MEMORY_GB << 30
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    try:
        sc = mm.simulate.make_pair(n, OVERLAP, SCALING_SNR, rng=seed)
        t0 = time.perf_counter()
        res = mm.merge_maps(sc.p, sc.q, sc.sigma, method=method, rng=0)
        conn.send(("ok", time.perf_counter() - t0, bool(mm.metrics.map_errors(sc, res)["transform_found"])))
    except MemoryError:
        conn.send((f"over {SCALING_MEMORY_GB} GB", np.nan, False))


def scaling(out: Path, sizes=SCALING_SIZES, time_limit: float = 120.0, methods=None) -> pd.DataFrame:
    """Seconds per merge against map size, one merge at a time in a child process; writes scaling.csv / .md."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")  # the children inherit the compiled kernels of the warm-up below
    methods = list(methods or ["consensus", *[p for p in PEER_PAIRS if importlib.util.find_spec(PEER_MODULES[p])]])
    warm = mm.simulate.make_pair(20, OVERLAP, SCALING_SNR, rng=0)
    rows = []
    for method in methods:
        mm.merge_maps(warm.p, warm.q, warm.sigma, method=method, rng=0)
        stopped = None
        for n in sorted(sizes):
            for seed in range(SCALING_PAIRS):
                if stopped:
                    rows.append({"method": method, "n_landmarks": n, "seed": seed, "status": f"not run ({stopped})",
                                 "seconds": np.nan, "found": False})
                    continue
                recv, send = ctx.Pipe(duplex=False)
                child = ctx.Process(target=timed_merge, args=(send, method, n, seed))
                child.start()
                send.close()  # so that a child that dies leaves the pipe at its end
                status, secs, found = f"over {time_limit:g} s", np.nan, False
                if recv.poll(time_limit):
                    try:
                        status, secs, found = recv.recv()
                    except EOFError:
                        child.join()
                        status = f"failed (exit {child.exitcode})"
                if child.is_alive():
                    child.kill()
                child.join()
                recv.close()
                if status != "ok":
                    stopped = f"{status} at {n}"
                rows.append({"method": method, "n_landmarks": n, "seed": seed, "status": status, "seconds": secs,
                             "found": found})
                print(rows[-1], flush=True)
                # Written after every merge, so that a run stopped early keeps what it measured.
                write_scaling(pd.DataFrame(rows), out, sizes, time_limit, methods)
    return pd.DataFrame(rows)


def write_scaling(df: pd.DataFrame, out: Path, sizes, time_limit: float, methods) -> None:
    """scaling.csv and scaling.md: per method and size, the median seconds of the merges that finished."""
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "scaling.csv", index=False, float_format="%.4g")
    lines = [f"Seconds per merge (median of the pairs that finished; found / pairs), 30 dB, strip layout, "
             f"overlap {OVERLAP}, one merge at a time, limit {time_limit:g} s and {SCALING_MEMORY_GB} GB a merge.",
             "", "| method | " + " | ".join(f"{n} landmarks" for n in sorted(sizes)) + " |",
             "|---|" + "---|" * len(sizes)]
    for method in methods:
        parts = []
        for n in sorted(sizes):
            r = df[(df["method"] == method) & (df["n_landmarks"] == n)]
            ok = r[r["status"] == "ok"]
            text = f"{np.median(ok['seconds']):.3g} s ({int(ok['found'].sum())}/{len(ok)})" if len(ok) else ""
            bad = r[r["status"] != "ok"]["status"]
            if len(bad):
                text = (text + "; " if text else "") + bad.iloc[0]
            parts.append(text or "not yet run")
        lines.append(f"| {method} | " + " | ".join(parts) + " |")
    (out / "scaling.md").write_text("\n".join(lines) + "\n")


def calibration_scores(job) -> dict:
    """``peer_shares``, kept in ``CELL_ROWS`` as soon as it is done (and read back from there)."""
    peer, n = job
    count = SLOW_CALIBRATION_PAIRS.get((peer, n), CALIBRATION_PAIRS[n])
    key = _rows_key(peer, (kept_row, peer_shares), (OVERLAP, CALIBRATION_SNR, CALIBRATION_SEED))
    return kept_row(CELL_ROWS / f"calibration_{peer}_{n}_{count}_{key}.json", peer_shares, (peer, n, count))


def peer_shares(job) -> dict:
    """A peer's inlier shares on ``count`` unrelated calibration pairs of a map size at 30 dB."""
    peer, n, count = job
    shares = np.array([len(PEER_PAIRS[peer](mm.simulate.make_pair(n, OVERLAP, CALIBRATION_SNR,
                                                                  rng=CALIBRATION_SEED + i, unrelated=True))) / n
                       for i in range(count)])
    top = np.sort(shares)[::-1]
    # At most one pair may reach the threshold: just above the second-largest share (counts are integers).
    need = (np.round(top[1] * n) + 1) / n
    return {"peer": peer, "n_landmarks": n, "pairs": count, "max_share": top[0], "second_share": top[1],
            "threshold_share": need}


def calibrate(out: Path, processes: int = 2, methods=None) -> pd.DataFrame:
    """The acceptance thresholds of ``methods`` (default: every installed peer; see the module docstring);
    writes calibration.csv / .md, keeping the other peers' rows."""
    peers = [p for p in PEER_PAIRS if importlib.util.find_spec(PEER_MODULES[p]) and (not methods or p in methods)]
    jobs = [(p, n) for p in peers for n in CALIBRATION_PAIRS]
    jobs.sort(key=lambda j: -j[1])
    if processes == 1:
        df = pd.DataFrame(map(calibration_scores, jobs))
    else:
        with Pool(processes) as pool:
            df = pd.DataFrame(pool.map(calibration_scores, jobs, chunksize=1))
    if (out / "calibration.csv").is_file():
        old = pd.read_csv(out / "calibration.csv")
        order = {peer: k for k, peer in enumerate(PEER_PAIRS)}
        df = pd.concat([old[~old["peer"].isin(peers)], df]).sort_values(
            ["n_landmarks", "peer"], ascending=[False, True], key=lambda c: c.map(order) if c.name == "peer" else c)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "calibration.csv", index=False, float_format="%.4g")
    (out / "calibration.md").write_text(df.to_markdown(index=False, floatfmt=".3g") + "\n")
    return df


def accepting_every_inlier_set(method: str):
    """A peer made to accept every inlier set of at least ``result.MIN_MATCHED_LANDMARKS`` pairs for the
    duration, so that its bound can be applied afterwards to the recorded inlier counts; other methods as
    they are."""
    if method not in PEER_BOUNDS:
        return contextlib.nullcontext()
    module, name = PEER_BOUNDS[method]
    return mock.patch.object(module, name, {size: 0 for size in getattr(module, name)})


@functools.cache
def _rows_key(method: str, functions=None, settings=()) -> str:
    """The digest that keys kept rows of ``method``: the library sources it runs (a peer: ``peer_sources``;
    our methods: all of them), the functions that compute the rows (not the tables drawn from them; by
    default those of an ``--equal-rate`` chunk) and the module ``settings`` they read."""
    library = Path(mm.__file__).resolve().parent
    files = peer_sources(method) if method in PEER_BOUNDS else library_sources()
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.as_posix().encode() + (library / path).read_bytes())
    for function in functions or (outcome_chunk, accepting_every_inlier_set):
        digest.update(inspect.getsource(function).encode())
    if settings:
        digest.update(repr(settings).encode())
    return digest.hexdigest()[:12]


def chunk_path(job) -> Path:
    method, layout, n, snr, kind, first, count = job
    return EQUAL_RATE_ROWS / f"{method}_{layout}_{n}_{snr:g}_{kind}_{first}_{count}_{_rows_key(method)}.csv"


def outcome_chunk(job) -> pd.DataFrame:
    """One chunk of ``--equal-rate``: ``method`` on the pairs of seeds [first, first + count) of a cell's
    ``kind`` (related, unrelated, tuning): each pair's seed, whether it merged, whether with the right
    transform, and how many landmark pairs it matched (a peer's inliers: here it accepts any inlier set)."""
    method, layout, n, snr, kind, first, count = job
    path = chunk_path(job)
    if path.is_file():
        return pd.read_csv(path)
    seeds = (CALIBRATION_SEED if kind == "tuning" else 0) + np.arange(first, first + count)
    scen = mm.simulate.make_pairs(n, OVERLAP, snr, [int(s) for s in seeds], unrelated=kind != "related",
                                  layout=layout)
    with accepting_every_inlier_set(method):
        merged = mm.merge_batch(scen.p, scen.q, scen.sigma, method=method, rng=0)
    err = mm.metrics.map_errors_batch(scen, merged)
    found = err["matched"] & err["transform_found"] if kind == "related" else np.zeros(len(seeds), bool)
    rows = pd.DataFrame({"seed": seeds, "merged": err["matched"], "found": found, "pairs": err["n_pairs"]})
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_suffix(".part")
    rows.to_csv(part, index=False)
    part.replace(path)  # a stopped run leaves no half-written chunk
    return rows


def equal_rate_cells(landmarks=None) -> list[tuple]:
    """(layout, n, SNR) of ``EQUAL_RATE_CELLS``, those of maps of ``landmarks`` landmarks when given."""
    return [(layout, n, snr) for layout, cells in EQUAL_RATE_CELLS.items() for n, snr in cells
            if landmarks is None or n in landmarks]


def equal_rate_jobs(methods, pairs: int, cells) -> list[tuple]:
    """The chunks of the cells: reported related and unrelated pairs, and a peer's tuning pairs."""
    jobs = []
    for (layout, n, snr), method in itertools.product(cells, methods):
        reported = fewer_pairs(EQUAL_RATE_SLOW, method, n, snr, pairs)
        if not reported:
            continue
        kinds = [("related", reported), ("unrelated", reported)]
        kinds += [("tuning", EQUAL_RATE_TUNING)] if method in PEER_BOUNDS else []
        jobs += [(method, layout, n, snr, kind, first, min(EQUAL_RATE_CHUNK, count - first))
                 for kind, count in kinds for first in range(0, count, EQUAL_RATE_CHUNK)]
    # CPD's chunks and the large maps first, so that the workers finish together.
    jobs.sort(key=lambda j: (j[0] != "cpd", -j[2]))
    return jobs


def tuned_bound(inliers) -> int:
    """The least inlier count that lets at most a share ``EQUAL_RATE`` of the tuning pairs' ``inliers``
    through (and never below ``result.MIN_MATCHED_LANDMARKS``)."""
    top = np.sort(np.asarray(inliers))[::-1]
    allowed = int(np.floor(EQUAL_RATE * len(top)))
    return max(MIN_MATCHED_LANDMARKS, int(top[allowed]) + 1 if allowed < len(top) else 0)


def accepted_rates(rel: pd.DataFrame, accepted_rel, accepted_unrel) -> dict:
    """Transform found (count, rate and its Wilson interval) and wrong merges among the related pairs ``rel``
    a rule accepts (``accepted_rel``), and false merges among the unrelated ones it accepts."""
    found = int((accepted_rel & rel.found).sum())
    lo, hi = wilson(found, len(rel))
    return {"found": found, "found_rate": found / len(rel), "found_lo": float(lo), "found_hi": float(hi),
            "wrong_merges": int((accepted_rel & ~rel.found).sum()), "false_merges": int(accepted_unrel.sum())}


def equal_rate_table(rows: pd.DataFrame, oracle: dict) -> pd.DataFrame:
    """Per cell and method: the found rate, wrong and false merges at the cell's bound (a peer's: the least
    inlier count that lets at most ``EQUAL_RATE`` of its tuning pairs through), and a peer's at its shipped
    bound beside it."""
    out = []
    for (layout, n, snr, method), cell in rows.groupby(["layout", "n_landmarks", "snr_db", "method"], observed=True):
        rel, unrel, tune = (cell[cell.kind == kind] for kind in ("related", "unrelated", "tuning"))
        row = {"layout": layout, "n_landmarks": n, "snr_db": snr, "method": method, "pairs": len(rel)}
        if method in PEER_BOUNDS:
            bound = tuned_bound(tune["pairs"])
            shipped = max(MIN_MATCHED_LANDMARKS, min_inliers(getattr(*PEER_BOUNDS[method]), n, n))
            row.update(tuning_pairs=len(tune), bound=bound, shipped_bound=shipped,
                       shipped_found=int((rel.found & (rel["pairs"] >= shipped)).sum()),
                       shipped_false_merges=int((unrel["pairs"] >= shipped).sum()))
            accepted_rel, accepted_unrel = rel["pairs"] >= bound, unrel["pairs"] >= bound
        else:
            accepted_rel, accepted_unrel = rel.merged, unrel.merged
        row.update(accepted_rates(rel, accepted_rel, accepted_unrel),
                   correspondence_oracle_found=oracle[layout, n, snr])
        out.append(row)
    df = pd.DataFrame(out)
    return df.merge(detector_limits(), on=["layout", "n_landmarks", "snr_db"], how="left")


def chunk_rows(pool, jobs, methods) -> pd.DataFrame:
    """Every chunk of ``jobs`` (``outcome_chunk``, on ``pool``), labelled with its method, cell and kind."""
    frames = []
    for k, (job, rows) in enumerate(zip(jobs, pool.imap(outcome_chunk, jobs))):
        frames.append(rows.assign(method=job[0], layout=job[1], n_landmarks=job[2], snr_db=float(job[3]),
                                  kind=job[4]))
        print(f"{k + 1}/{len(jobs)} {job[:5]} seeds {job[5]}+{job[6]}", flush=True)
    rows = pd.concat(frames, ignore_index=True)
    rows["method"] = pd.Categorical(rows["method"], methods)
    return rows


def equal_rate(out: Path, processes: int = 2, methods=None, pairs: int = EQUAL_RATE_PAIRS,
               landmarks=None) -> pd.DataFrame:
    """consensus and the installed peers at one false-merge rate per cell (module docstring), on the cells of
    maps of ``landmarks`` landmarks when given; writes equal_rate.csv / .md."""
    methods = [m for m in (methods or available_methods()) if m == "consensus" or m in PEER_BOUNDS]
    cells = equal_rate_cells(landmarks)
    with Pool(processes) as pool:
        rows = chunk_rows(pool, equal_rate_jobs(methods, pairs, cells), methods)
        found = pool.starmap(oracle_found, [(*cell, pairs) for cell in cells])
    oracle = {(layout, n, float(snr)): k / pairs for (layout, n, snr), k in zip(cells, found)}
    df = equal_rate_table(rows, oracle)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "equal_rate.csv", index=False, float_format="%.4g")
    write_equal_rate(df, out / "equal_rate.md", pairs)
    equal_rate_figure(df, out)
    return df


def one_bound_table(rows: pd.DataFrame, floors=ONE_BOUND_FLOORS) -> pd.DataFrame:
    """Per floor of ``floors`` (``snr_from``), peer and cell of ``rows`` (``chunk_rows``) from that SNR up: the
    found rate, wrong and false merges at the peer's one bound per map size (the largest of its cell bounds at
    that size from the floor up, ``bound_cell`` the cell that sets it), and at its bound in the cell
    (``cell_*``)."""
    keys = ["method", "layout", "n_landmarks", "snr_db"]
    cells = {key: cell for key, cell in rows.groupby(keys, observed=True)}
    cell_bound = {key: tuned_bound(cell[cell.kind == "tuning"]["pairs"]) for key, cell in cells.items()}
    out = []
    for floor in floors:
        one = {}
        for (method, layout, n, snr), bound in cell_bound.items():
            if snr >= floor and bound > one.get((method, n), (0,))[0]:
                one[method, n] = (bound, f"{layout} {snr:g} dB")
        for key, cell in cells.items():
            method, layout, n, snr = key
            if snr < floor:
                continue
            rel, unrel = cell[cell.kind == "related"], cell[cell.kind == "unrelated"]
            row = dict(zip(keys, key), snr_from=floor, pairs=len(rel), bound=one[method, n][0],
                       bound_cell=one[method, n][1], cell_bound=cell_bound[key])
            for prefix, bound in (("", row["bound"]), ("cell_", row["cell_bound"])):
                rates = accepted_rates(rel, rel["pairs"] >= bound, unrel["pairs"] >= bound)
                row.update({prefix + name: value for name, value in rates.items()})
            out.append(row)
    return pd.DataFrame(out)


def one_bound(out: Path, processes: int = 2, methods=None, pairs: int = EQUAL_RATE_PAIRS,
              landmarks=None) -> pd.DataFrame:
    """The installed peers (or ``methods``) with one bound per map size on ``ONE_BOUND_CELLS`` (those of maps
    of ``landmarks`` landmarks when given; module docstring); writes one_bound.csv / .md, keeping the rows of
    peers and sizes not run."""
    methods = [m for m in (methods or available_methods()) if m in PEER_BOUNDS]
    if not methods:
        raise SystemExit("--one-bound: no peer installed (pip install 'mapmerge[peers]'; tools/build_peers.sh)")
    cells = [cell for cell in ONE_BOUND_CELLS if landmarks is None or cell[1] in landmarks]
    with Pool(processes) as pool:
        df = one_bound_table(chunk_rows(pool, equal_rate_jobs(methods, pairs, cells), methods))
    path = out / "one_bound.csv"
    if path.is_file():
        old = pd.read_csv(path)
        rerun = old.set_index(["method", "n_landmarks"]).index.isin(df.set_index(["method", "n_landmarks"]).index)
        df = pd.concat([old[~rerun], df], ignore_index=True)
    df = df.sort_values(["n_landmarks", "layout", "snr_db", "method", "snr_from"], ignore_index=True)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(path, index=False, float_format="%.4g")
    write_one_bound(df, out / "one_bound.md")
    return df


def write_one_bound(df: pd.DataFrame, path: Path) -> None:
    """one_bound.md: one row per cell, one column per peer."""
    methods = list(dict.fromkeys(df["method"]))
    bounds = df.drop_duplicates(["method", "n_landmarks", "snr_from"])
    lines = [(f"Each peer with one acceptance bound per map size, as `consensus_count` has one level per size: "
              f"the largest of its bounds in the cells of that size from an SNR up, both layouts (each cell's the "
              f"least inlier count that lets at most {EQUAL_RATE:g} of the cell's {EQUAL_RATE_TUNING:,} unrelated "
              f"tuning pairs through, seeds {CALIBRATION_SEED:,} + i), so that it holds whatever the SNR and "
              f"layout of a user's maps above that SNR: from 10 dB, as the count levels, and from 15 dB. "
              f"Transform found on related pairs, % [95 % Wilson interval] (pairs), wrong merges and false merges "
              f"on as many unrelated pairs (seeds 0, 1, ...) at each, and the found rate at the peer's bound in "
              f"the cell (results/peers/equal_rate.md, which knows the cell's SNR)."), "",
             "One bound per size: " + "; ".join(f"{r.method} at {r.n_landmarks} landmarks from {r.snr_from:g} dB: "
                                                 f"{r.bound} inliers (set by {r.bound_cell})"
                                                 for r in bounds.itertuples()), "",
             "| layout, n, SNR | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for (n, layout, snr), cell in df.groupby(["n_landmarks", "layout", "snr_db"], sort=False):
        parts = []
        for method in methods:
            rows = cell[cell.method == method]
            if not len(rows):
                parts.append("not run")
                continue
            first = rows.iloc[0]
            parts.append("; ".join([f"from {r.snr_from:g} dB, bound {int(r.bound)}: {100 * r.found_rate:.1f} "
                                    f"[{100 * r.found_lo:.1f}, {100 * r.found_hi:.1f}] ({int(r.pairs)}), "
                                    f"{int(r.wrong_merges)} wrong, {int(r.false_merges)} false"
                                    for r in rows.itertuples()] +
                                   [f"in the cell, bound {int(first.cell_bound)}: {100 * first.cell_found_rate:.1f} "
                                    f"%, {int(first.cell_false_merges)} false"]))
        lines.append(f"| {layout}, {n}, {snr:g} dB | " + " | ".join(parts) + " |")
    path.write_text("\n".join(lines) + "\n")


def equal_rate_figure(df: pd.DataFrame, out: Path) -> list[Path]:
    """equal_rate.png / .pdf: transform found against SNR at one false-merge rate, a panel per layout and map
    size: consensus, the peers and the two limits (six curves at most)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from experiments.figures import STYLE, legend_entries, save_figure

    layouts, sizes = list(dict.fromkeys(df["layout"])), sorted(df["n_landmarks"].unique())
    methods = list(dict.fromkeys(df["method"].astype(str)))
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(len(layouts), len(sizes), figsize=(2.6 * len(sizes), 2.4 * len(layouts) + 0.6),
                                 squeeze=False, sharex=True, sharey=True)
        for (row, layout), (col, n) in itertools.product(enumerate(layouts), enumerate(sizes)):
            ax, part = axes[row, col], df[(df["layout"] == layout) & (df["n_landmarks"] == n)]
            for k, m in enumerate(methods):
                g = part[part["method"].astype(str) == m].sort_values("snr_db")
                if len(g):
                    ax.errorbar(g.snr_db, g.found_rate, yerr=[g.found_rate - g.found_lo, g.found_hi - g.found_rate],
                                color=f"C{k}", marker="o", ms=2.5, lw=1.0, capsize=1.5, label=m)
            limits = part.drop_duplicates("snr_db").sort_values("snr_db")
            ax.plot(limits.snr_db, limits.correspondence_oracle_found, color="0.3", lw=1.0, ls="--",
                    label="limit: fit knowing every correspondence")
            det = limits.dropna(subset=["detector_found"])
            if len(det):
                ax.plot(det.snr_db, det.detector_found, color="k", lw=1.4, ls=":",
                        label="limit: exhaustive detector, 1e-3 false alarms")
            ax.set_title(f"{layout}, {n} landmarks")
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3, lw=0.4)
            if row == len(layouts) - 1:
                ax.set_xlabel("SNR (dB)")
            if col == 0:
                ax.set_ylabel("transform found")
        fig.legend(*legend_entries(axes), loc="lower center", ncol=3, frameon=False, fontsize=6)
        fig.suptitle(f"At most {EQUAL_RATE:g} false merges per cell, {OVERLAP:.0%} common landmarks")
        fig.tight_layout(rect=(0, 0.08, 1, 1))
        return save_figure(fig, out, "equal_rate")


def write_equal_rate(df: pd.DataFrame, path: Path, pairs: int) -> None:
    """equal_rate.md: one row per cell, one column per method."""
    methods = list(dict.fromkeys(df["method"].astype(str)))
    lines = [(f"Every method at one false-merge rate per cell. Transform found on related pairs, % [95 % Wilson "
              f"interval] (pairs), wrong merges (related pairs merged with a transform that is not found), false "
              f"merges on as many unrelated pairs (seeds 0, 1, ...). consensus: its own test. A peer: its bound "
              f"(inliers) set in the cell on {EQUAL_RATE_TUNING:,} unrelated tuning pairs (seeds "
              f"{CALIBRATION_SEED:,} + i) to let at most {EQUAL_RATE:g} of them through; in brackets its shipped "
              f"bound (set at 30 dB) on the same pairs. Limits: the fit knowing every correspondence ({pairs:,} "
              f"related pairs) and the exhaustive detector (results/detector/, its own pairs, at a false-alarm "
              f"rate of 1e-3: the empirical quantile of 10,000 null pairs on the small maps, a tail fitted to "
              f"100 null pairs at 100 landmarks)."), "",
             "| layout, n, SNR | " + " | ".join(methods) + " | oracle fit | detector |",
             "|---|" + "---|" * (len(methods) + 2)]
    for (layout, n, snr), cell in df.groupby(["layout", "n_landmarks", "snr_db"], sort=False):
        by = cell.set_index("method")
        parts = []
        for m in methods:
            if m not in by.index:
                parts.append(not_run(m, n))
                continue
            r = by.loc[m]
            text = (f"{100 * r.found_rate:.1f} [{100 * r.found_lo:.1f}, {100 * r.found_hi:.1f}] ({int(r.pairs)}), "
                    f"{int(r.wrong_merges)} wrong, {int(r.false_merges)} false")
            if m in PEER_BOUNDS:
                text += (f"; bound {int(r.bound)} (shipped {int(r.shipped_bound)}: "
                         f"{100 * r.shipped_found / r.pairs:.1f} %, {int(r.shipped_false_merges)} false)")
            parts.append(text)
        first = cell.iloc[0]
        det = "" if pd.isna(first.detector_found) else f"{100 * first.detector_found:.1f}"
        lines.append(f"| {layout}, {n}, {snr:g} dB | " + " | ".join(parts) +
                     f" | {100 * first.correspondence_oracle_found:.1f} | {det} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("results/peers"))
    ap.add_argument("--calibrate", action="store_true", help="set the peers' thresholds instead")
    ap.add_argument("--scaling", action="store_true", help="time per merge against map size instead")
    ap.add_argument("--equal-rate", action="store_true", help="every method at one false-merge rate per cell")
    ap.add_argument("--one-bound", action="store_true", help="each peer with one bound per small-map size")
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--layout", choices=list(CELLS), default="strip")
    ap.add_argument("--methods", nargs="+", help="default: every available method")
    ap.add_argument("--pairs", type=int, help=f"related (and unrelated) pairs per cell at most (default: {PAIRS}, "
                                              f"{EQUAL_RATE_PAIRS} with --equal-rate)")
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SCALING_SIZES))
    ap.add_argument("--landmarks", type=int, nargs="+",
                    help="--equal-rate, --one-bound: only the cells of these map sizes")
    ap.add_argument("--time-limit", type=float, default=120.0, help="seconds a merge may take (--scaling)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.calibrate:
        df = calibrate(args.out, args.processes, args.methods)
    elif args.equal_rate:
        df = equal_rate(args.out, args.processes, args.methods, args.pairs or EQUAL_RATE_PAIRS, args.landmarks)
    elif args.one_bound:
        df = one_bound(args.out, args.processes, args.methods, args.pairs or EQUAL_RATE_PAIRS, args.landmarks)
    elif args.scaling:
        df = scaling(args.out, args.sizes, args.time_limit, args.methods)
    else:
        df = compare(args.out, args.processes, args.layout, args.methods, args.pairs or PAIRS)
    print(df.to_string())
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
