"""Where consensus's power goes on small maps: the search's bound at one transform, and held-out null pairs.

    python -m experiments.small_maps --landmarks 10 20 --snrs 20 30 --pairs 10000 --bound-pairs 2000 \
        --out results/detector/small

Checks beside ``experiments.detector``'s tables (``stages``), chosen with
``--checks``:

1. ``bound``: the global search's a contrario test at one fixed transform.
   On unrelated pairs of the detector's tuning seeds (300000+k), the
   mixture model of ``mapmerge.search`` (pair noise r, prior
   ``search.MIXTURE_PRIOR``) is evaluated at the pair's own drawn motion,
   a transform chosen without looking at the landmarks, and
   ``Mixture.null_log_tail`` bounds P(Λ >= observed) there. If the bound
   were exact, a fraction u of the pairs would have a bound <= log u; the
   table gives the fraction at u = 1e-1, 1e-2, 1e-3 and the empirical
   1e-3 quantile of the bound: how loose Chernoff's bound is on a few
   landmarks, apart from the hypothesis count;
2. ``holdout``: ``experiments.detector.consensus_outcome`` on unrelated
   pairs of seeds 600000+k (kept per cell in ``holdout_<n>_<snr>_<code digest>.csv``, so that only the
   same code reuses them), disjoint from the tuning seeds the thresholds
   of ``stages`` were set on: how many pass consensus's defaults, and each
   of the ``stages`` table's empirical thresholds (read from
   ``stages.csv`` in ``--out``), so the false-merge rates of the calibrated
   rules are measured on pairs they were not chosen on;
3. ``calibrated``: consensus with its triangle test's acceptance
   (``consensus.MATCH_NFA``) raised to the ``--quantile`` quantile of the
   triangle log NFA on the cell's unrelated tuning pairs (``pairs.csv`` in
   ``--out``, seeds 300000+k), on the detector's related pairs (seeds
   100000+k) and on the held-out unrelated pairs (seeds 600000+k): found
   rate, wrong merges of related pairs (with their median rotation error,
   how many are over 5° and how many pair a landmark wrongly) and false
   merges, what a threshold calibrated per cell would give.
   ``calibrated_<n>_<snr>_<quantile>_<code digest>.csv`` keeps the pairs'
   outcomes;
4. ``acceptance``: how often the triangle test's NFA falls to each of
   ``NFA_LEVELS`` by chance, on ``--tuning-pairs`` unrelated pairs (seeds
   300000+k, the global search declining so that only that test decides),
   and how often it then accepts a right or a wrong transform on the
   related pairs (seeds 100000+k): the evidence for ``consensus.MATCH_NFA``
   (and the passes at the level it gives the cell's size).
   On maps of at most ``HOLDOUT_MAX_LANDMARKS`` landmarks it also merges
   ``--pairs`` held-out unrelated pairs (seeds 600000+k) with ``consensus``
   as shipped, search included: the false merges of its rule;
5. ``levels``: consensus as shipped (the search included) but with its
   triangle test accepting at each of ``--levels`` in turn (what-if runs
   of ``consensus.MATCH_NFA``): false merges on ``--pairs`` held-out
   unrelated pairs (seeds 600000+k) and the found rate and wrong merges
   on ``--related`` related pairs of seeds 0+k, the pairs
   ``experiments.peers --equal-rate`` gives every peer, so the rates
   compare with the peers' at one false-merge rate;
6. ``statistics``: the triangle test alone (the search declining) on
   ``--tuning-pairs`` unrelated tuning pairs (seeds 300000+k), the peers'
   ``--related`` related pairs (seeds 0+k) and ``--pairs`` held-out
   unrelated pairs (seeds 600000+k). Each ranking of ``RANKINGS`` (the
   NFA, the association count, the count NFA) gets a threshold per cell
   as the peers do (at most ``--rate`` of the tuning pairs through); the
   count NFA also gets one level per map size (``size_level``), as
   consensus would ship it. Found rates, wrong merges, held-out false
   passes, the triangle stage's ceiling and the best peer of ``--peers``;
7. ``count_levels``: the levels of ``consensus.SEARCH_COUNT_LEVELS`` and
   ``consensus.COUNT_LEVELS``. On the statistics check's unrelated tuning
   pairs (seeds 300000+k) the global search alone (``search_rows``, kept
   like the statistics rows: its own test and the count NFA of its best
   hypothesis) and the count NFA of the triangle test: per map size the
   loosest search level at which at most ``consensus.SEARCH_ALLOWED``
   tuning pairs merge in every cell, then the loosest triangle level at
   which at most ``consensus.TUNING_ALLOWED`` merge, the search's merges
   counted first (``count_level_table``);
8. ``count``: the ``consensus_count`` method (the count NFA at
   ``consensus.COUNT_LEVELS``, the search included): false merges on
   ``--pairs`` held-out unrelated pairs (seeds ``--holdout-seed``+k,
   600000 unless given), found rate and
   wrong merges on ``--related`` related pairs (seeds 0+k), beside
   consensus and the best peer of ``--peers``;
9. ``reference``: no merging. Per small-map cell (up to 20 landmarks) of
   ``results/peers/equal_rate.csv`` (``--peers``), consensus and the
   default ``consensus_count`` (the count check's ``count.csv`` in
   ``--out``) beside the best outside peer at one false-merge rate, the
   best peer with one bound per map size (``--one-bound-peers``, a peer
   it lacks at its rate in the cell) and the exhaustive detector at 1e-3
   (``limit.csv`` in ``--out``, strip layout, on its own pairs, with
   consensus's find on them): found rates with their intervals, the
   ratios, and whether each of ours is ahead, level (intervals overlap)
   or behind the peer;
10. ``oracle_count``: where the default's remaining power goes. On the
    ``--related`` related pairs (seeds 0+k), the landmarks associated
    (``association.associate_batch``) under the fit on every true
    correspondence, refitted on that association: the share whose
    transform meets the found rule and whose count NFA with one hypothesis
    passes the search's count level of its size
    (``consensus.search_count_level``), as if a stage had proposed the true
    transform (without consensus's EM step), beside ``consensus_count``'s
    found rate on the same pairs. Where the two are close, the loss is in
    the acceptance test, not in finding the transform.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
from joblib import Parallel, delayed
from scipy.spatial import ConvexHull

import mapmerge as mm
from mapmerge.alignment import fit_alignments
from mapmerge.association import associate_batch
from mapmerge.exhaustive import Mixture, bump_height, pair_noise

from . import detector
from .aggregate import save_table
from .detector import REPORTED_SEED, STAGE_STATISTICS, TUNING_SEED, consensus_outcome
from .intervals import wilson
from .trials import code_digest

#: Unrelated pairs held out from every threshold: seeds HOLDOUT_SEED + k.
HOLDOUT_SEED = 600_000
#: Tail probabilities at which the bound's calibration is read.
LEVELS = (1e-1, 1e-2, 1e-3)
#: Bounds on the triangle test's NFA at which the ``acceptance`` check counts passes.
NFA_LEVELS = (1e-6, 1e-4, 1e-3, 1e-2)
#: The ``acceptance`` check merges held-out pairs in full (the search included) on maps of at most this
#: many landmarks, where the bound is loose and a merge fast (up to the first size ``consensus.MATCH_NFA``
#: holds at 1e-4); larger maps get the tuning count only.
HOLDOUT_MAX_LANDMARKS = 30
#: Where the ``acceptance`` check keeps each cell's pairs (20,000 rows a cell: not committed).
ROWS = Path("outputs") / "small_maps"
#: Map pairs per ``merge_batch`` call of the ``acceptance`` check.
BATCH = 100
#: ``consensus_outcome``'s columns (``detector.MEASURES``).
OUTCOME = ("consensus_merged", "consensus_found", "consensus_correct", "consensus_wrong", "tri_log_nfa",
           "tri_hypotheses", "tri_pairs", "tri_found", "search_log_nfa", "search_log_hypotheses", "search_log_tail",
           "search_found")


def fixed_transform_bound(n: int, snr: float, seed: int) -> tuple[float, int, float]:
    """(Λ, q landmarks inside p's hull, log tail bound) of the search's model at an unrelated pair's own motion."""
    sc = mm.simulate.make_pair(n, 0.75, snr, rng=seed, unrelated=True)
    r, hull = pair_noise(sc.sigma), ConvexHull(sc.p)
    prior = mm.search.MIXTURE_PRIOR
    model = Mixture.of_map(sc.p, r, bump_height(len(sc.p), hull.volume, r, prior), prior, hull)
    value, inside = model.log_lr(sc.q, sc.theta, sc.t)
    return value, inside, float(model.null_log_tail([value], [inside])[0])


def bound_table(n: int, snr: float, pairs: int) -> dict:
    bounds = np.array([fixed_transform_bound(n, snr, TUNING_SEED + k)[2] for k in range(pairs)])
    return {"n_landmarks": n, "snr_db": snr, "pairs": pairs,
            **{f"fraction_bound_le_{u:g}": float(np.mean(bounds <= np.log(u))) for u in LEVELS},
            "bound_quantile_1e-3": float(np.quantile(bounds, 1e-3)), "median_bound": float(np.median(bounds))}


def holdout_table(n: int, snr: float, pairs: int, stages: pd.DataFrame, out: Path) -> dict:
    """Null passes of ``consensus`` as shipped and of ``stages``' thresholds on held-out unrelated pairs (strip
    layout)."""
    path = out / f"holdout_{n}_{snr:g}_{code_digest(detector.__file__)[:12]}.csv"
    rows = pd.read_csv(path) if path.is_file() else None
    if rows is None or len(rows) != pairs:
        seeds = HOLDOUT_SEED + np.arange(pairs)
        rows = pd.DataFrame([consensus_outcome(n, "strip", snr, int(seed), True) for seed in seeds], columns=OUTCOME)
        rows.insert(0, "seed", seeds)
        rows.to_csv(path, index=False, float_format="%.10g")
    cell = stages[(stages.n_landmarks == n) & (stages.snr_db == snr)].iloc[0]
    row = {"n_landmarks": n, "snr_db": snr, "holdout_pairs": pairs,
           "consensus_false_merges": int(rows.consensus_merged.astype(bool).sum())}
    for stat in STAGE_STATISTICS:
        row[f"{stat}_null_pass"] = int(np.sum(rows[stat] < cell[f"{stat}_threshold"]))
    tri = rows.tri_log_nfa < cell.combined_tri_threshold
    row["combined_null_pass"] = int(np.sum(tri | (rows.search_log_nfa < cell.combined_search_threshold)))
    return row


def triangle_acceptance(nfa: float):
    """consensus's triangle test accepting at NFA <= nfa on maps of every size (``consensus.MATCH_NFA``, read
    at call time) for the duration: what-if runs of a threshold, not a setting of the library."""
    return mock.patch.object(mm.consensus, "MATCH_NFA", {np.inf: nfa})


def merge_outcome(n: int, snr: float, seed: int, unrelated: bool) -> tuple[bool, bool, float, int]:
    """(merged, transform found, rotation error in degrees, wrong landmark pairs) of consensus on one of the
    detector's strip-layout pairs (NaN and 0 when not merged)."""
    sc = detector._pair(n, "strip", snr, seed, unrelated)
    err = mm.metrics.map_errors(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus"))
    return (bool(err["matched"]), bool(err["matched"] and not unrelated and err["transform_found"]),
            float(abs(err["rot_err_deg"])), int(err["wrong_pairs"]))


def calibrated_table(n: int, snr: float, related: int, pairs: int, quantile: float, tuning: pd.DataFrame,
                     out: Path) -> dict:
    """consensus with its triangle threshold at the tuning pairs' ``quantile`` (strip layout)."""
    null = tuning[(tuning.n_landmarks == n) & (tuning.snr_db == snr) & tuning.unrelated.astype(bool)]
    log_t = float(np.quantile(null.tri_log_nfa, quantile))
    path = out / f"calibrated_{n}_{snr:g}_{quantile:g}_{code_digest(detector.__file__)[:12]}.csv"
    rows = pd.read_csv(path) if path.is_file() else None
    if rows is None or len(rows) != related + pairs:
        seeds = [(False, REPORTED_SEED + k) for k in range(related)] + [(True, HOLDOUT_SEED + k) for k in range(pairs)]
        with triangle_acceptance(float(np.exp(log_t))):
            outcomes = [merge_outcome(n, snr, seed, unrelated) for unrelated, seed in seeds]
        rows = pd.DataFrame([(u, s, *o) for (u, s), o in zip(seeds, outcomes)],
                            columns=["unrelated", "seed", "merged", "found", "rot_err_deg", "wrong_pairs"])
        rows.to_csv(path, index=False)
    rel, hold = rows[~rows.unrelated], rows[rows.unrelated]
    wrong = rel[rel.merged & ~rel.found]
    return {"n_landmarks": n, "snr_db": snr, "quantile": quantile, "tuning_pairs": len(null),
            "tri_log_nfa_threshold": log_t, "related_pairs": len(rel), "found_rate": rel.found.mean(),
            "wrong_merges": len(wrong), "wrong_median_rot_err_deg": wrong.rot_err_deg.median(),
            "wrong_over_5_deg": int((wrong.rot_err_deg > 5).sum()),
            "wrong_with_wrong_landmark_pairs": int((wrong.wrong_pairs > 0).sum()), "holdout_pairs": len(hold),
            "false_merges": int(hold.merged.sum())}


def _ratio(a: float, b: float) -> float:
    """a / b, NaN where b is 0 or NaN (nothing to compare with)."""
    return a / b if b > 0 else np.nan


def best_peer(cell: pd.DataFrame) -> pd.Series:
    """The outside method of most found in one cell of ``experiments.peers --equal-rate``'s table."""
    peers = cell[(cell.method != "consensus") & (cell.pairs > 0)]
    return peers.loc[peers.found_rate.idxmax()]


def cell_rows(table: pd.DataFrame, layout: str, n: int, snr: float) -> pd.DataFrame:
    """The rows of one (layout, landmarks, SNR) cell of a table."""
    return table[(table.layout == layout) & (table.n_landmarks == n) & (table.snr_db == snr)]


def verdict(lo: float, hi: float, peer: pd.Series) -> str:
    """"ahead", "behind" or "level" (the intervals overlap) of a found rate's interval [lo, hi] against a peer's."""
    return "ahead" if lo > peer.found_hi else "behind" if hi < peer.found_lo else "level"


def peer_columns(equal_rate: pd.DataFrame, layout: str, n: int, snr: float, intervals: dict) -> dict:
    """The best peer of a cell of ``experiments.peers --equal-rate``'s table and the verdict of each found-rate
    interval of ``intervals`` ({column: (lo, hi)}) against it; "n/a" where the table has no such cell."""
    cell = cell_rows(equal_rate, layout, n, snr)
    if not len(cell):
        return {"best_peer": "n/a", "peer_found": np.nan, "peer_lo": np.nan, "peer_hi": np.nan,
                **{column: "n/a" for column in intervals}}
    best = best_peer(cell)
    return {"best_peer": best.method, "peer_found": best.found_rate, "peer_lo": best.found_lo,
            "peer_hi": best.found_hi, **{column: verdict(lo, hi, best) for column, (lo, hi) in intervals.items()}}


def one_bound_peer(cell: pd.DataFrame, one_bound: pd.DataFrame) -> pd.Series:
    """``best_peer`` of one cell of ``experiments.peers --equal-rate``'s table when each peer has one bound per
    map size: its rate in ``one_bound`` (``experiments.peers --one-bound``'s rows of one floor), or for a peer
    that table lacks its rate at the cell's own bound (``source`` "cell"), which one bound per size can only
    lower."""
    keys, rates = ["method", "layout", "n_landmarks", "snr_db"], ["found_rate", "found_lo", "found_hi"]
    cell = cell.merge(one_bound[keys + rates], on=keys, how="left", suffixes=("", "_one_bound"))
    has = cell.found_rate_one_bound.notna()
    for rate in rates:
        cell[rate] = cell[rate + "_one_bound"].where(has, cell[rate])
    return best_peer(cell.assign(source=np.where(has, "one bound", "cell")))


def reference_table(equal_rate: pd.DataFrame, limit: pd.DataFrame, count: pd.DataFrame,
                    one_bound: pd.DataFrame) -> pd.DataFrame:
    """consensus and the default ``consensus_count`` (``count``: the count check's table) against the best peer
    at one false-merge rate, the best peer with one bound per map size (``one_bound_peer``) and the detector at
    1e-3, per small-map cell. The one bound holds from each floor of ``one_bound`` (``snr_from``) up: columns
    ``*_from_<floor>db``."""
    rows = []
    small = equal_rate[equal_rate.n_landmarks <= 20]
    floors = sorted(one_bound.snr_from.unique())
    for (layout, n, snr), cell in small.groupby(["layout", "n_landmarks", "snr_db"]):
        ours, best = cell[cell.method == "consensus"].iloc[0], best_peer(cell)
        default = cell_rows(count, layout, n, snr).iloc[0]
        one_bound_columns = {}
        for floor in floors:
            one = one_bound_peer(cell, one_bound[one_bound.snr_from == floor])
            one_bound_columns.update({
                f"one_bound_peer_from_{floor:g}db": f"{one.method} ({one.source})",
                f"one_bound_peer_found_from_{floor:g}db": one.found_rate,
                f"one_bound_peer_lo_from_{floor:g}db": one.found_lo,
                f"one_bound_peer_hi_from_{floor:g}db": one.found_hi,
                f"default_vs_one_bound_peer_from_{floor:g}db": verdict(default.found_lo, default.found_hi, one)})
        found = cell_rows(limit, layout, n, snr)
        # The detector's pairs are its own (seeds 100000+), with consensus's find on them; NaN without a row.
        detector = found.iloc[0] if len(found) else pd.Series({"found_rate": np.nan, "consensus_found_rate": np.nan})
        rows.append({"layout": layout, "n_landmarks": n, "snr_db": snr, "pairs": int(ours.pairs),
                     "consensus_found": ours.found_rate, "consensus_lo": ours.found_lo,
                     "consensus_hi": ours.found_hi, "consensus_false": int(ours.false_merges),
                     "best_peer": best.method, "peer_pairs": int(best.pairs), "peer_found": best.found_rate,
                     "peer_lo": best.found_lo, "peer_hi": best.found_hi,
                     "vs_peer": verdict(ours.found_lo, ours.found_hi, best),
                     "ratio_to_peer": _ratio(ours.found_rate, best.found_rate),
                     "default_found": default.found_rate, "default_lo": default.found_lo,
                     "default_hi": default.found_hi, "default_holdout_false": int(default.false_merges),
                     "default_holdout_pairs": int(default.holdout_pairs),
                     "default_vs_peer": verdict(default.found_lo, default.found_hi, best),
                     **one_bound_columns,
                     "detector_found": detector.found_rate,
                     "consensus_found_detector_pairs": detector.consensus_found_rate,
                     "ratio_to_detector": _ratio(detector.consensus_found_rate, detector.found_rate),
                     "oracle_fit_found": ours.correspondence_oracle_found})
    return pd.DataFrame(rows)


def acceptance_rows(n: int, layout: str, snr: float, seeds, unrelated: bool, search: bool) -> list[tuple]:
    """(seed, triangle log NFA (inf: no test), its transform found, merged, landmark associations it tested,
    the log of their ``consensus.count_nfa_batch``) of consensus on the detector's pairs ``seeds``, in
    batches; without ``search`` the triangle test alone decides."""
    rows = []
    for start in range(0, len(seeds), BATCH):
        chunk = [int(s) for s in seeds[start:start + BATCH]]
        sc = mm.simulate.make_pairs(n, 0.75, snr, chunk, unrelated=unrelated, layout=layout)
        with detector.recorded_tests(search) as seen:
            merged = mm.merge_batch(sc.p, sc.q, sc.sigma, method="consensus").matched
        for b, seed in enumerate(chunk):
            tests = seen.get(sc.p[b].tobytes(), {})
            nfa, _, k, theta, t = tests.get("triangles", (np.inf, 0, 0, None, None))
            found = theta is not None and not unrelated and mm.metrics.transform_found(sc[b], theta, t)
            with np.errstate(divide="ignore"):
                rows.append((seed, float(np.log(nfa)), bool(found), bool(merged[b]), k,
                             float(np.log(tests.get("count", np.inf)))))
    return rows


def merged_counts(n: int, layout: str, snr: float, related: int, holdout: int, methods=("consensus",),
                  oracle: bool = False, holdout_seed: int = HOLDOUT_SEED) -> list[dict]:
    """Each of ``methods`` under whatever acceptance is in force, one dict per method: false merges on
    ``holdout`` held-out unrelated pairs (seeds ``holdout_seed``+k; the first method only, the others get
    none), found rate (with its interval) and wrong merges on ``related`` related pairs of seeds 0+k, the
    pairs ``experiments.peers --equal-rate`` gives every peer; ``wrong_over_5_deg``: the wrong merges whose
    rotation is over 5° off (the others are near misses of the found rule). With ``oracle``, also
    ``oracle_found``, the related pairs whose fit on every true correspondence
    (``metrics.correspondence_oracle_transform``, once per pair for all methods) meets the found rule, and
    ``wrong_oracle_found``, the wrong merges among them: the rest are pairs that no association could merge
    within the rule."""
    counts = [dict.fromkeys(("false_merges", "found", "wrong_merges", "wrong_over_5_deg", "oracle_found",
                             "wrong_oracle_found"), 0) for _ in methods]
    for start in range(0, holdout, BATCH):
        seeds = [holdout_seed + k for k in range(start, min(start + BATCH, holdout))]
        sc = mm.simulate.make_pairs(n, 0.75, snr, seeds, unrelated=True, layout=layout)
        counts[0]["false_merges"] += int(mm.merge_batch(sc.p, sc.q, sc.sigma, method=methods[0]).matched.sum())
    for start in range(0, related, BATCH):
        seeds = list(range(start, min(start + BATCH, related)))
        sc = mm.simulate.make_pairs(n, 0.75, snr, seeds, unrelated=False, layout=layout)
        if oracle:
            fits = [mm.metrics.correspondence_oracle_transform(sc[b]) for b in range(len(seeds))]
            reachable = np.array([mm.metrics.transform_found(sc[b], f.theta, f.t) for b, f in enumerate(fits)])
        for method, c in zip(methods, counts):
            err = mm.metrics.map_errors_batch(sc, mm.merge_batch(sc.p, sc.q, sc.sigma, method=method))
            c["found"] += int((err["matched"] & err["transform_found"]).sum())
            wrong = err["matched"] & ~err["transform_found"]
            c["wrong_merges"] += int(wrong.sum())
            c["wrong_over_5_deg"] += int(np.sum(wrong & (np.abs(err["rot_err_deg"]) > 5)))
            if oracle:
                c["oracle_found"] += int(reachable.sum())
                c["wrong_oracle_found"] += int((wrong & reachable).sum())
    rows = []
    for k, c in enumerate(counts):
        lo, hi = wilson(c["found"], related)
        pairs = holdout if k == 0 else 0
        rows.append({"holdout_seed": holdout_seed, "holdout_pairs": pairs, "false_merges": c["false_merges"],
                     "false_upper": float(wilson(c["false_merges"], pairs)[1]) if pairs else np.nan,
                     "related_pairs": related,
                     "found_rate": c["found"] / related, "found_lo": float(lo), "found_hi": float(hi),
                     "wrong_merges": c["wrong_merges"], "wrong_over_5_deg": c["wrong_over_5_deg"],
                     **({"oracle_found": c["oracle_found"], "wrong_oracle_found": c["wrong_oracle_found"]}
                        if oracle else {})})
    return rows


def level_table(n: int, layout: str, snr: float, level: float, related: int, holdout: int) -> dict:
    """consensus with its triangle test accepting at NFA <= ``level`` (``merged_counts``)."""
    with triangle_acceptance(level):
        return {"n_landmarks": n, "layout": layout, "snr_db": snr, "match_nfa": level,
                **merged_counts(n, layout, snr, related, holdout)[0]}


def count_table(n: int, layout: str, snr: float, related: int, holdout: int, equal_rate: pd.DataFrame,
                holdout_seed: int = HOLDOUT_SEED) -> dict:
    """``consensus_count`` (the count NFA at ``consensus.COUNT_LEVELS`` and ``consensus.SEARCH_COUNT_LEVELS``):
    ``merged_counts`` with the oracle's columns, and consensus's found rate and wrong merges on the same
    related pairs, beside the best peer's at one false-merge rate; ``vs_consensus``, ``vs_peer``:
    ``verdict`` of consensus_count's found rate."""
    counted, ours = merged_counts(n, layout, snr, related, holdout, ("consensus_count", "consensus"), oracle=True,
                                  holdout_seed=holdout_seed)
    row = {"n_landmarks": n, "layout": layout, "snr_db": snr,
           "log_level": np.log(mm.consensus.triangle_test(n, "count")[1]),
           "search_log_level": mm.consensus.search_count_level(n), **counted}
    row.update(consensus_found=ours["found_rate"], consensus_lo=ours["found_lo"], consensus_hi=ours["found_hi"],
               consensus_wrong=ours["wrong_merges"], consensus_wrong_over_5_deg=ours["wrong_over_5_deg"],
               consensus_wrong_oracle_found=ours["wrong_oracle_found"],
               vs_consensus=verdict(row["found_lo"], row["found_hi"], pd.Series({"found_lo": ours["found_lo"],
                                                                               "found_hi": ours["found_hi"]})))
    row.update(peer_columns(equal_rate, layout, n, snr, {"vs_peer": (row["found_lo"], row["found_hi"])}))
    return row


#: The columns of ``acceptance_rows``.
ACCEPTANCE_COLUMNS = ("seed", "tri_log_nfa", "tri_found", "merged", "tri_pairs", "tri_log_count_nfa")


def oracle_count_table(n: int, layout: str, snr: float, related: int) -> dict:
    """The ``oracle_count`` check of one cell (module docstring); a pair with under 3 true correspondences
    counts as not accepted."""
    level, found, accepted = mm.consensus.search_count_level(n), 0, 0
    for start in range(0, related, BATCH):
        seeds = list(range(start, min(start + BATCH, related)))
        sc = mm.simulate.make_pairs(n, 0.75, snr, seeds, layout=layout)
        err = mm.metrics.map_errors_batch(sc, mm.merge_batch(sc.p, sc.q, sc.sigma, method="consensus_count"))
        found += int((err["matched"] & err["transform_found"]).sum())
        true = sc.ids_p[:, :, None] == sc.ids_q[:, None, :]
        rows = np.flatnonzero(true.sum(axis=(1, 2)) >= 3)
        P, Q, sigma, B = sc.p[rows], sc.q[rows], sc.sigma[rows], len(rows)
        trial, i, j = np.nonzero(true[rows])
        theta, t, _, cov = fit_alignments(trial, P[trial, i], Q[trial, j], sigma, B)
        trial, pairs, _ = associate_batch(P, Q, theta, t, cov, sigma, with_margin=False)
        theta, t, _, cov = fit_alignments(trial, P[trial, pairs[:, 0]], Q[trial, pairs[:, 1]], sigma, B)
        nfa = mm.consensus.count_nfa_batch(P, Q, theta, t, cov, trial, pairs, np.ones(B), sigma)
        right = np.array([mm.metrics.transform_found(sc[b], theta[k], t[k]) for k, b in enumerate(rows)], bool)
        accepted += int(np.sum((np.log(nfa) <= level) & right))
    return {"n_landmarks": n, "layout": layout, "snr_db": snr, "related_pairs": related, "search_log_level": level,
            "found_rate": found / related, "oracle_accepted_rate": accepted / related}


def kept_rows(check: str, n: int, layout: str, snr: float, sets, make=acceptance_rows,
              columns=ACCEPTANCE_COLUMNS) -> list[pd.DataFrame]:
    """``make(n, layout, snr, seeds, *args)`` rows (``columns``) of each set (kind, first seed, count, *args) of
    a cell, one frame per set; kept in ``ROWS/<check>_<n>_<layout>_<snr>_<code digest>.csv`` and read back while
    the code and the counts are the same."""
    path = ROWS / f"{check}_{n}_{layout}_{snr:g}_{code_digest(detector.__file__)[:12]}.csv"
    rows = pd.read_csv(path) if path.is_file() else None
    if rows is None or [int(np.sum(rows.kind == kind)) for kind, *_ in sets] != [c for _, _, c, *_ in sets]:
        rows = pd.DataFrame([(kind, *row) for kind, base, count, *args in sets
                             for row in make(n, layout, snr, base + np.arange(count), *args)],
                            columns=["kind", *columns])
        path.parent.mkdir(parents=True, exist_ok=True)
        rows.to_csv(path, index=False, float_format="%.10g")
    return [rows[rows.kind == kind] for kind, *_ in sets]


def acceptance_table(n: int, layout: str, snr: float, tuning: int, related: int, holdout: int) -> dict:
    """The triangle test's passes at each of ``NFA_LEVELS`` on unrelated tuning pairs and its found rate on
    related pairs, alone; consensus's shipped rule's false merges on held-out unrelated pairs (maps of at most
    ``HOLDOUT_MAX_LANDMARKS`` landmarks)."""
    holdout = holdout if n <= HOLDOUT_MAX_LANDMARKS else 0
    null, rel, hold = kept_rows("acceptance", n, layout, snr, (
        ("tuning", TUNING_SEED, tuning, True, False), ("related", REPORTED_SEED, related, False, False),
        ("holdout", HOLDOUT_SEED, holdout, True, True)))
    row = {"n_landmarks": n, "layout": layout, "snr_db": snr, "tuning_pairs": len(null)}
    for level in NFA_LEVELS:
        row[f"tuning_pass_{level:g}"] = int(np.sum(null.tri_log_nfa <= np.log(level)))
    row["match_nfa"] = mm.consensus.match_level(n)
    row["tuning_pass_shipped"] = int(np.sum(null.tri_log_nfa <= np.log(row["match_nfa"])))
    row["related_pairs"] = len(rel)
    for level in NFA_LEVELS:
        accepted = rel.tri_log_nfa <= np.log(level)
        row[f"found_{level:g}"] = float(np.mean(accepted & rel.tri_found))
        row[f"wrong_{level:g}"] = float(np.mean(accepted & ~rel.tri_found))
    merges = int(hold.merged.sum())
    row.update(holdout_pairs=len(hold), holdout_false_merges=merges if len(hold) else np.nan,
               holdout_false_upper=float(wilson(merges, len(hold))[1]) if len(hold) else np.nan)
    return row


#: The statistics check's rankings of a match, as sort keys of kept rows (strongest evidence first): its
#: NFA (consensus's test), its associations with the NFA breaking ties, and its ``consensus.count_nfa_batch``.
RANKINGS = {"nfa": lambda r: zip(r.tri_log_nfa),
            "count_first": lambda r: zip(-r.tri_pairs, r.tri_log_nfa),
            "count_nfa": lambda r: zip(r.tri_log_count_nfa)}
#: Tuning pairs a level per map size lets through in the worst of its cells: 3 of 10,000 keeps the 95 %
#: upper bound of the chance rate below 1e-3, the rule the shipped levels follow.
SIZE_ALLOWED = 3


def statistics_frames(n: int, layout: str, snr: float, tuning: int, related: int, holdout: int):
    """The statistics check's kept rows of a cell, triangle test alone: unrelated tuning pairs (seeds 300000+k),
    the peers' related pairs (seeds 0+k), held-out unrelated pairs (seeds 600000+k)."""
    return kept_rows("statistics", n, layout, snr, (
        ("tuning", TUNING_SEED, tuning, True, False), ("related", 0, related, False, False),
        ("holdout", HOLDOUT_SEED, holdout, True, False)))


def cell_limit(log_count_nfa: np.ndarray, by_search: np.ndarray, allowed: int | None = None) -> float:
    """The log count NFA of the first tuning pair a cell must stop so that at most ``allowed`` (default
    ``SIZE_ALLOWED``) of its tuning pairs merge, those merged already (``by_search``) spent first: when those
    alone are as many or more, the cell's first pair not merged already (it may add none); inf when none
    need stopping."""
    spare = max(0, (SIZE_ALLOWED if allowed is None else allowed) - int(by_search.sum()))
    ranked = np.sort(log_count_nfa[~by_search])
    return ranked[spare] if spare < len(ranked) else np.inf


def level_below(limits) -> float:
    """The loosest log level, rounded down to 0.01, strictly below every cell's limit."""
    limit = np.min(limits)
    level = np.floor(limit * 100) / 100
    return level if level < limit else level - 0.01


def size_level(frames) -> float:
    """The count NFA's level for one map size, triangle test alone: the loosest that lets at most
    ``SIZE_ALLOWED`` tuning pairs through in every cell (``frames``: each cell's ``statistics_frames``)."""
    return min(cell_limit(null.tri_log_count_nfa.to_numpy(), np.zeros(len(null), dtype=bool))
               for null, _, _ in frames)


def search_rows(n: int, layout: str, snr: float, seeds) -> list[tuple]:
    """(seed, merged by the search's own test, log count NFA of its best hypothesis) of the global search
    alone (``consensus.search_count_nfa``) on the unrelated pairs ``seeds``: the merges ``consensus_count``'s
    fallback adds to its triangle test's, whatever that test's level, at any level of its own."""
    rows = []
    for start in range(0, len(seeds), BATCH):
        chunk = [int(s) for s in seeds[start:start + BATCH]]
        sc = mm.simulate.make_pairs(n, 0.75, snr, chunk, unrelated=True, layout=layout)
        *_, nfa, log_count_nfa = mm.consensus.search_count_nfa(sc.p, sc.q, sc.sigma)
        rows += zip(chunk, (nfa <= mm.search.SEARCH_NFA).tolist(), log_count_nfa.tolist())
    return rows


def count_level_frames(n: int, layout: str, snr: float, tuning: int):
    """A cell's unrelated tuning pairs (seeds 300000+k): the triangle test alone (the statistics check's kept
    rows, or only their tuning set) and the global search alone (``search_rows``) on the same pairs."""
    null, = kept_rows("statistics", n, layout, snr, (("tuning", TUNING_SEED, tuning, True, False),))
    search, = kept_rows("search", n, layout, snr, (("tuning", TUNING_SEED, tuning),), search_rows,
                        ("seed", "merged", "log_count_nfa"))
    return null, search


def count_level_table(cells: dict) -> pd.DataFrame:
    """``consensus_count``'s levels for each map size, on each cell's unrelated tuning pairs (``cells``:
    {(n, layout, SNR): ``count_level_frames``}). First the search's (``consensus.SEARCH_COUNT_LEVELS``): the
    loosest, rounded down to 0.01 in log, at which the search merges at most ``consensus.SEARCH_ALLOWED``
    tuning pairs in every cell of the size, its own test's merges spent first; then the triangle test's
    (``consensus.COUNT_LEVELS``): the loosest at which at most ``consensus.TUNING_ALLOWED`` tuning pairs merge
    in every cell, the search's merges at its level spent first. ``search_limit``, ``cell_limit``: the log
    count NFA of the first tuning pair the cell must stop (``cell_limit``: where the merges spent first
    already reach the allowance, its first pair not merged already)."""
    table = pd.DataFrame([{"n_landmarks": n, "layout": layout, "snr_db": snr, "tuning_pairs": len(null),
                           "search_test_merges": int(search.merged.sum()),
                           "search_limit": cell_limit(search.log_count_nfa.to_numpy(),
                                                      search.merged.to_numpy(dtype=bool),
                                                      mm.consensus.SEARCH_ALLOWED)}
                          for (n, layout, snr), (null, search) in cells.items()])
    table["search_log_level"] = table.groupby("n_landmarks").search_limit.transform(level_below)
    by_search = [search.merged.to_numpy(dtype=bool) | (search.log_count_nfa.to_numpy() <= lvl)
                 for (_, search), lvl in zip(cells.values(), table.search_log_level)]
    table["search_merges"] = [int(merged.sum()) for merged in by_search]
    table["cell_limit"] = [cell_limit(null.tri_log_count_nfa.to_numpy(), merged,
                                      mm.consensus.TUNING_ALLOWED)
                           for (null, _), merged in zip(cells.values(), by_search)]
    table["log_level"] = table.groupby("n_landmarks").cell_limit.transform(level_below)
    table["tuning_merges"] = [int(np.sum((null.tri_log_count_nfa.to_numpy() <= lvl) | merged))
                              for (null, _), merged, lvl in zip(cells.values(), by_search, table.log_level)]
    return table


def _passes(r: pd.DataFrame, key, limit) -> np.ndarray:
    """Which tested rows sort before ``limit`` under a ranking's key."""
    return np.isfinite(r.tri_log_nfa.to_numpy()) & np.array([k < limit for k in key(r)], dtype=bool)


def _rates(name: str, rel: pd.DataFrame, hold: pd.DataFrame, accepted: np.ndarray, false: int) -> dict:
    found = int(np.sum(accepted & rel.tri_found.to_numpy()))
    lo, hi = wilson(found, len(rel))
    return {f"{name}_found": found / len(rel), f"{name}_lo": float(lo), f"{name}_hi": float(hi),
            f"{name}_wrong": int(np.sum(accepted & ~rel.tri_found.to_numpy())), f"{name}_holdout_false": false,
            f"{name}_false_upper": float(wilson(false, len(hold))[1])}


def statistics_table(n: int, layout: str, snr: float, frames, rate: float, level: float,
                     equal_rate: pd.DataFrame) -> dict:
    """The triangle test alone, each ranking with its threshold set per cell as the peers' are, and the count
    NFA at ``level``, one level for the map size (``size_level``).

    A per-cell threshold lets at most ``rate`` x the cell's tuning pairs through, the peers' rule in
    ``experiments.peers --equal-rate``; ``<ranking>_limit`` is the first tuning pair it stops (its sort key).
    Found rates and wrong merges are on the related pairs, false passes on the held-out pairs
    (``statistics_frames``). ``ceiling``: the share of related pairs whose triangle stage proposes a right
    transform, before any test; ``shipped_found``: what the shipped level finds.
    """
    null, rel, hold = frames
    allowed = int(rate * len(null))
    row = {"n_landmarks": n, "layout": layout, "snr_db": snr, "tuning_pairs": len(null), "allowed": allowed,
           "related_pairs": len(rel), "ceiling": float(rel.tri_found.mean()),
           "shipped_found": float(np.mean((rel.tri_log_nfa <= np.log(mm.consensus.match_level(n))) & rel.tri_found))}
    for name, key in RANKINGS.items():
        ranked = sorted(key(null))
        limit = ranked[allowed] if allowed < len(ranked) else (np.inf, np.inf)
        row.update({f"{name}_limit": ", ".join(f"{v:.3g}" for v in limit),
                    f"{name}_tuning_pass": int(_passes(null, key, limit).sum()),
                    **_rates(name, rel, hold, _passes(rel, key, limit), int(_passes(hold, key, limit).sum()))})
    # The count NFA at one level for every cell of the size, as consensus would ship it.
    null_pass, rel_pass, hold_pass = (r.tri_log_count_nfa.to_numpy() < level for r in (null, rel, hold))
    row.update({"size_level_log": level, "size_level_tuning_pass": int(null_pass.sum()),
                **_rates("size_level", rel, hold, rel_pass, int(hold_pass.sum()))})
    row.update(peer_columns(equal_rate, layout, n, snr, {f"{name}_vs_peer": (row[f"{name}_lo"], row[f"{name}_hi"])
                                                          for name in ("count_first", "size_level")}))
    return row


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="The search's bound at one transform; held-out null pairs.")
    parser.add_argument("--landmarks", type=int, nargs="+", default=[10, 20])
    parser.add_argument("--snrs", type=float, nargs="+", default=[20.0, 30.0])
    parser.add_argument("--pairs", type=int, default=10_000, help="held-out unrelated pairs per cell")
    parser.add_argument("--holdout-seed", type=int, default=HOLDOUT_SEED,
                        help="first seed of the count check's held-out unrelated pairs")
    parser.add_argument("--bound-pairs", type=int, default=2_000, help="unrelated pairs per cell of the bound check")
    parser.add_argument("--out", default="results/detector/small")
    parser.add_argument("--peers", default="results/peers/equal_rate.csv",
                        help="experiments.peers --equal-rate's table, for the reference check")
    parser.add_argument("--one-bound-peers", default="results/peers/one_bound.csv",
                        help="experiments.peers --one-bound's table, for the reference check")
    parser.add_argument("--checks", nargs="+",
                        choices=("bound", "holdout", "calibrated", "acceptance", "levels", "statistics",
                                 "count_levels", "count", "reference", "oracle_count"),
                        default=["bound", "holdout"])
    parser.add_argument("--layouts", nargs="+", choices=("strip", "interleaved"), default=["strip"],
                        help="layouts of the acceptance, levels, statistics and count checks")
    parser.add_argument("--tuning-pairs", type=int, default=10_000, help="unrelated tuning pairs per cell of the "
                        "acceptance and statistics checks")
    parser.add_argument("--rate", type=float, default=1e-3,
                        help="share of tuning pairs the statistics check's thresholds let through")
    parser.add_argument("--n-jobs", type=int, default=1, help="cells run in parallel (every check but reference)")
    parser.add_argument("--related", type=int, default=500,
                        help="related pairs per cell of the calibrated, acceptance, levels and statistics checks")
    parser.add_argument("--quantile", type=float, default=2e-4, help="tuning quantile of the calibrated check")
    parser.add_argument("--levels", type=float, nargs="+", default=list(NFA_LEVELS[1:]),
                        help="triangle acceptance levels of the levels check")
    args = parser.parse_args(argv)
    counts = {"--pairs": args.pairs, "--bound-pairs": args.bound_pairs, "--n-jobs": args.n_jobs,
              "--related": args.related, "--tuning-pairs": args.tuning_pairs}
    if min(counts.values()) < 1:
        raise SystemExit(f"{', '.join(counts)} must be >= 1, got {', '.join(map(str, counts.values()))}")
    if not all(0 < v < 1 for v in (args.quantile, args.rate, *args.levels)):
        raise SystemExit(f"--quantile, --rate and --levels must be in (0, 1), got {args.quantile}, {args.rate} and "
                         f"{args.levels}")
    out = Path(args.out)
    cells = list(itertools.product(args.landmarks, args.snrs))
    layout_cells = list(itertools.product(args.landmarks, args.layouts, args.snrs))
    if "bound" in args.checks:
        table = pd.DataFrame(Parallel(n_jobs=args.n_jobs)(delayed(bound_table)(n, snr, args.bound_pairs)
                                                          for n, snr in cells))
        for path in save_table(table, out / "bound"):
            print(path, flush=True)
    if "holdout" in args.checks:
        if not (out / "stages.csv").is_file():
            raise SystemExit(f"--out {out}: no stages.csv (run experiments.detector there first)")
        stages = pd.read_csv(out / "stages.csv")
        table = pd.DataFrame(Parallel(n_jobs=args.n_jobs)(delayed(holdout_table)(n, snr, args.pairs, stages, out)
                                                          for n, snr in cells))
        for path in save_table(table, out / "holdout"):
            print(path)
    if "calibrated" in args.checks:
        if not (out / "pairs.csv").is_file():
            raise SystemExit(f"--out {out}: no pairs.csv (run experiments.detector there first)")
        tuning = pd.read_csv(out / "pairs.csv")
        table = pd.DataFrame([calibrated_table(n, snr, args.related, args.pairs, args.quantile, tuning, out)
                              for n, snr in cells])
        for path in save_table(table, out / "calibrated"):
            print(path)
    if "acceptance" in args.checks:
        out.mkdir(parents=True, exist_ok=True)
        table = pd.DataFrame(Parallel(n_jobs=args.n_jobs)(
            delayed(acceptance_table)(n, layout, snr, args.tuning_pairs, args.related, args.pairs)
            for n, layout, snr in layout_cells))
        for path in save_table(table, out / "acceptance"):
            print(path)
    if "levels" in args.checks:
        out.mkdir(parents=True, exist_ok=True)
        jobs = list(itertools.product(args.landmarks, args.layouts, args.snrs, args.levels))
        table = pd.DataFrame(Parallel(n_jobs=args.n_jobs)(
            delayed(level_table)(n, layout, snr, level, args.related, args.pairs) for n, layout, snr, level in jobs))
        for path in save_table(table, out / "levels"):
            print(path)
    if {"statistics", "count"} & set(args.checks):
        if not Path(args.peers).is_file():
            raise SystemExit(f"statistics and count checks: {args.peers} not found (run experiments.peers "
                             "--equal-rate first)")
        equal_rate = pd.read_csv(args.peers)
        out.mkdir(parents=True, exist_ok=True)
    if "statistics" in args.checks:
        frames = dict(zip(layout_cells, Parallel(n_jobs=args.n_jobs)(
            delayed(statistics_frames)(*cell, args.tuning_pairs, args.related, args.pairs) for cell in layout_cells)))
        levels = {n: size_level([f for (m, _, _), f in frames.items() if m == n]) for n in args.landmarks}
        table = pd.DataFrame([statistics_table(*cell, frames[cell], args.rate, levels[cell[0]], equal_rate)
                              for cell in layout_cells])
        for path in save_table(table, out / "statistics"):
            print(path)
    if "count_levels" in args.checks:
        out.mkdir(parents=True, exist_ok=True)
        frames = Parallel(n_jobs=args.n_jobs)(delayed(count_level_frames)(*cell, args.tuning_pairs)
                                              for cell in layout_cells)
        for path in save_table(count_level_table(dict(zip(layout_cells, frames))), out / "count_levels"):
            print(path)
    if "count" in args.checks:
        table = pd.DataFrame(Parallel(n_jobs=args.n_jobs)(
            delayed(count_table)(*cell, args.related, args.pairs, equal_rate, args.holdout_seed)
            for cell in layout_cells))
        for path in save_table(table, out / "count"):
            print(path)
    if "oracle_count" in args.checks:
        table = pd.DataFrame(Parallel(n_jobs=args.n_jobs)(delayed(oracle_count_table)(*cell, args.related)
                                                          for cell in layout_cells))
        for path in save_table(table, out / "oracle_count"):
            print(path)
    if "reference" in args.checks:
        inputs = (Path(args.peers), out / "limit.csv", out / "count.csv", Path(args.one_bound_peers))
        missing = [path for path in inputs if not path.is_file()]
        if missing:
            raise SystemExit(f"reference check: {missing[0]} not found (run experiments.peers --equal-rate and "
                             f"--one-bound, experiments.detector --out {out} and this module's count check first)")
        table = reference_table(*map(pd.read_csv, inputs))
        for path in save_table(table, out / "reference"):
            print(path)


if __name__ == "__main__":
    main()
