"""The exhaustive ML detector's limit curve: could any matcher have merged these pairs? (results/detector/)

    python -m experiments.detector                  # 100 pairs per cell, 0-17.5 dB, both layouts
    python -m experiments.detector --trials 20      # a quick look
    python -m experiments.detector --snrs 15 --layouts strip --trials 1000 --out results/detector/15db
    python -m experiments.detector --landmarks 10 20 --snrs 20 --layouts strip --out results/detector/small

Pairs already in ``pairs.csv`` are not computed again (each pair depends on
its seed alone), so an interrupted or extended run resumes, and a rerun
only rebuilds the tables. Each row carries the digest of the code, numpy's
and scipy's versions and the machine's arithmetic that computed it
(``code``): a row written by other code (or before rows carried one) is
computed again.

Per layout (strip; interleaved with p_detect 0.9) and SNR, on the paper's
Fig. 1 scenario (100 landmarks per map, 75 % common; ``--landmarks`` for
others, such as Fig. 3's 10 and 20):

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
   (``mapmerge.metrics.transform_found``); ``ml_accurate_rate`` counts the
   pairs whose ML transform is within 1° and σ whatever the statistic (no
   threshold at all, so no false-merge guarantee: an upper reference);
3. on the same pairs, ``consensus`` (``mapmerge.merge_maps`` with its
   defaults and the same σ, but not the layout's prior): whether it merged,
   whether it found the transform and its correct and wrong landmark pairs,
   the latter against those of the oracle association (true transform and
   prior) and of the transform oracle (true transform only; both from
   ``mapmerge.metrics.oracle_pairs_batch``) on the pairs where consensus
   found the transform. The two are compared pair by pair;
4. on the same pairs, the correspondence oracle
   (``mapmerge.metrics.correspondence_oracle_transform``: the closed-form ML
   transform over every common landmark, paired by its true id):
   ``correspondence_found_rate`` counts the pairs it puts within 1° and σ,
   the transform's accuracy when nothing has to be found but the transform
   itself (at 10 dB its rotation error has a standard deviation of about
   half a degree, so even it misses 1° on some pairs).

The detector knows the true σ and the layout's prior, so it is a reference
(an oracle), not a method; its threshold, extrapolated from 100 null pairs,
is conservative, and below 12.5 dB ``consensus`` (whose search is accepted
by an a contrario bound) merges more. From 12.5 dB on every related pair is
far above the null (see the table's margins), so what limits it there is
the accuracy of its transform, not detection.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import itertools
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

import mapmerge as mm
from mapmerge.association import SHARED_RANGE

from .aggregate import ratio, save_table
from .trials import arithmetic_digest, code_digest, library_versions

SNRS = tuple(np.arange(0.0, 17.51, 2.5))
LAYOUTS = ("strip", "interleaved")
#: False alarms per unrelated pair allowed to the detector, as for the matchers' targets.
FALSE_ALARM = 1e-3
#: The null's exponential tail is fitted above this quantile.
TAIL_QUANTILE = 0.75
TUNING_SEED, REPORTED_SEED = 300_000, 100_000


#: Landmarks per map unless ``--landmarks`` says otherwise (the paper's Fig. 1 scenario).
LANDMARKS = 100


def _pairs(n: int, layout: str, snr: float, seed: int, unrelated: bool):
    return mm.simulate.make_pairs(n, 0.75, snr, [seed], unrelated=unrelated, layout=layout)


def _pair(n: int, layout: str, snr: float, seed: int, unrelated: bool):
    return _pairs(n, layout, snr, seed, unrelated)[0]


def statistic(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[float, bool, float]:
    """(max Λ, transform found, seconds) of one pair."""
    sc = _pair(n, layout, snr, seed, unrelated)
    clock = time.perf_counter()
    value, theta, t = mm.exhaustive.max_log_lr(sc.p, sc.q, sc.sigma, float(np.clip(sc.p_shared, *SHARED_RANGE)),
                                               sc.density)
    seconds = time.perf_counter() - clock
    return value, (not unrelated) and mm.metrics.transform_found(sc, theta, t), seconds


def consensus_outcome(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[bool, bool, int, int]:
    """(merged, transform found, correct pairs, wrong pairs) of ``consensus`` on the same pair."""
    sc = _pair(n, layout, snr, seed, unrelated)
    err = mm.metrics.map_errors(sc, mm.merge_maps(sc.p, sc.q, sc.sigma))
    return err["matched"], err["matched"] and not unrelated and err["transform_found"], err["correct_pairs"], \
        err["wrong_pairs"]


def oracle_outcome(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[int, int, int, int]:
    """(correct, wrong) pairs of the oracle association, then of the transform oracle; zeros for
    unrelated pairs, which have no truth."""
    if unrelated:
        return 0, 0, 0, 0
    oracle = mm.metrics.oracle_pairs_batch(_pairs(n, layout, snr, seed, unrelated))
    return tuple(int(oracle[f"{name}_{kind}_pairs"][0]) for name in ("oracle", "transform_oracle")
                 for kind in ("correct", "wrong"))


def correspondence_outcome(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[bool]:
    """Whether the transform fitted on every true correspondence is within 1° and σ (False when unrelated)."""
    if unrelated:
        return (False,)
    sc = _pair(n, layout, snr, seed, unrelated)
    fit = mm.metrics.correspondence_oracle_transform(sc)
    return (mm.metrics.transform_found(sc, fit.theta, fit.t),)


#: What is measured on each pair: the function and the columns it fills.
MEASURES = ((statistic, ("log_lr", "found", "seconds")),
            (consensus_outcome, ("consensus_merged", "consensus_found", "consensus_correct", "consensus_wrong")),
            (oracle_outcome, ("oracle_correct", "oracle_wrong", "transform_oracle_correct", "transform_oracle_wrong")),
            (correspondence_outcome, ("correspondence_found",)))


def null_threshold(null: np.ndarray) -> float:
    """Threshold at ``FALSE_ALARM`` from null statistics: an exponential tail above their ``TAIL_QUANTILE``."""
    u = float(np.quantile(null, TAIL_QUANTILE))
    beta = float(np.mean(null[null > u] - u))
    return u + beta * np.log((1 - TAIL_QUANTILE) / FALSE_ALARM)


JOB = ["n_landmarks", "layout", "snr_db", "seed", "unrelated"]
#: The column of ``pairs.csv`` naming the code that computed a row (``code_key``).
CODE = "code"
COLUMNS = JOB + [column for _, columns in MEASURES for column in columns] + [CODE]


@functools.cache
def code_key() -> str:
    """What a pair's measures depend on besides the pair: the library's and this module's code,
    numpy's and scipy's versions, and the machine's arithmetic (12 hex digits)."""
    key = {"code": code_digest(__file__), "libraries": library_versions(), "arithmetic": arithmetic_digest()}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]


def cell_jobs(n: int, layout: str, snr: float, trials: int) -> list[tuple]:
    """The null pairs (tuning seeds), then the related pairs (reported seeds), of one cell."""
    return [(int(n), layout, float(snr), int(seed), unrelated)
            for unrelated, base in ((True, TUNING_SEED), (False, REPORTED_SEED)) for seed in base + np.arange(trials)]


def _read(path: Path) -> pd.DataFrame:
    table = pd.read_csv(path)
    if "n_landmarks" not in table:  # written before maps of other sizes were measured
        table.insert(0, "n_landmarks", LANDMARKS)
    return table


def run_pairs(trials: int, n_jobs: int, path: Path, snrs=SNRS, layouts=LAYOUTS, landmarks=(LANDMARKS,)) -> pd.DataFrame:
    """Every measure of every null and related pair: one row each, in job order.

    ``path`` (``pairs.csv``) is read first and rewritten after each cell
    computed: measures it already holds are not computed again, unless
    other code wrote them (their ``code`` is not ``code_key()``), and its
    rows of other pairs (e.g. of a run with more trials) are kept.
    """
    known: dict[tuple, dict] = {}  # rows of this code
    other: dict[tuple, dict] = {}  # rows of other code: kept in the file until their pair is computed
    if path.is_file():
        old = _read(path)
        for job, row in zip(old[JOB].itertuples(index=False, name=None), old.drop(columns=JOB).to_dict("records")):
            values = {k: v for k, v in row.items() if not pd.isna(v)}
            (known if values.get(CODE) == code_key() else other)[job] = values
    jobs = []
    for n, layout, snr in itertools.product(landmarks, layouts, snrs):
        cell = cell_jobs(n, layout, snr, trials)
        changed = False
        for measure, columns in MEASURES:
            todo = [job for job in cell if not set(columns) <= known.get(job, {}).keys()]
            out = Parallel(n_jobs=n_jobs, batch_size=4)(delayed(measure)(*job) for job in todo)
            for job, values in zip(todo, out):
                known.setdefault(job, {CODE: code_key()}).update(zip(columns, values))
            changed |= bool(todo)
        jobs += cell
        if changed:
            rows = {**other, **known}
            listed = set(jobs)
            order = jobs + [job for job in rows if job not in listed]
            table = pd.DataFrame([{**dict(zip(JOB, job)), **rows[job]} for job in order], columns=COLUMNS)
            table.to_csv(path, index=False, float_format="%.10g")  # seconds: its one machine-dependent column
    # The table is built from the file's values, so a resumed run gives the same table as a fresh one.
    return pd.DataFrame(jobs, columns=JOB).merge(_read(path), on=JOB, how="left", validate="one_to_one")


def limit_table(runs: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for (n, layout, snr), g in runs.groupby(["n_landmarks", "layout", "snr_db"], sort=False):
        null, related = g[g.unrelated].log_lr.to_numpy(), g[~g.unrelated]
        found = related[related.consensus_found.astype(bool)]
        threshold = null_threshold(null)
        detected = related.log_lr.to_numpy() >= threshold
        rows.append({"n_landmarks": n, "layout": layout, "snr_db": snr, "null_pairs": len(null), "null_max": null.max(),
                     "threshold": threshold, "related_pairs": len(related),
                     "detected_rate": detected.mean(), "found_rate": (detected & related.found.to_numpy()).mean(),
                     # The ML transform's accuracy whatever its statistic: what no threshold could improve.
                     "ml_accurate_rate": related.found.mean(),
                     # Knowing every correspondence: the accuracy no matcher is expected to beat.
                     "correspondence_found_rate": related.correspondence_found.astype(bool).mean(),
                     "consensus_found_rate": related.consensus_found.mean(),
                     "consensus_false_merges": int(g[g.unrelated].consensus_merged.sum()),
                     # Association where consensus found the transform, against both oracles' on those pairs.
                     **{f"consensus_{kind}_vs_{name}": float(ratio(found[f"consensus_{kind}"].sum(),
                                                                  found[f"{name}_{kind}"].sum()))
                        for name in ("oracle", "transform_oracle") for kind in ("correct", "wrong")},
                     "median_related_log_lr": float(np.median(related.log_lr)),
                     "median_s": float(np.median(g.seconds))})
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="The exhaustive ML detector's limit curve.")
    parser.add_argument("--trials", type=int, default=100, help="pairs per cell, null and related each")
    parser.add_argument("--out", default="results/detector")
    parser.add_argument("--n-jobs", type=int, default=2)
    parser.add_argument("--snrs", type=float, nargs="+", default=SNRS, help="SNRs in dB (default: 0-17.5 by 2.5)")
    parser.add_argument("--layouts", nargs="+", choices=LAYOUTS, default=LAYOUTS)
    parser.add_argument("--landmarks", type=int, nargs="+", default=[LANDMARKS],
                        help=f"landmarks per map (default: {LANDMARKS})")
    args = parser.parse_args(argv)
    if args.trials < 8:
        raise SystemExit("--trials must be >= 8 (the null's tail fit needs them)")
    for n, snr in itertools.product(args.landmarks, args.snrs):
        try:
            mm.simulate.check_scenario(n, 0.75, snr, 1.0)
        except mm.simulate.ScenarioError as exc:
            # The overlap is fixed here: an overlap too small for 3 common landmarks means too few landmarks.
            flag, value = ("snrs", snr) if exc.argument == "snr_db" else ("landmarks", n)
            raise SystemExit(f"--{flag} {value!r}: {exc.rule}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = run_pairs(args.trials, args.n_jobs, out / "pairs.csv", args.snrs, args.layouts, args.landmarks)
    for path in save_table(limit_table(runs), out / "limit"):
        print(path)


if __name__ == "__main__":
    main()
