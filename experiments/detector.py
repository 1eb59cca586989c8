"""The exhaustive ML detector's limit curve: could any matcher have merged these pairs? (results/detector/)

    python -m experiments.detector                  # 100 pairs per cell, 0-17.5 dB, both layouts
    python -m experiments.detector --trials 20      # a quick look
    python -m experiments.detector --snrs 15 --layouts strip --trials 1000 --out results/detector/15db
    python -m experiments.detector --landmarks 10 20 --snrs 20 --layouts strip --out results/detector/small
    python -m experiments.detector --landmarks 10 20 --snrs 15 20 25 30 --layouts strip --trials 500 \
        --null-pairs 10000 --false-alarm 1e-3 --maximiser pairs --n-jobs 1 --out results/detector/small

Pairs already in ``pairs.csv`` are not computed again (each pair depends on
its seed alone), so an interrupted or extended run resumes, and a rerun
only rebuilds the tables (``--tables-only`` rebuilds them from the file's
rows whatever code wrote them, computing nothing). Each row carries the digest of the code, numpy's
and scipy's versions and the machine's arithmetic that computed it
(``code``): a row written by other code (or before rows carried one) is
computed again.

Per layout (strip; interleaved with p_detect 0.9) and SNR, on the paper's
Fig. 1 scenario (100 landmarks per map, 75 % common; ``--landmarks`` for
others, such as Fig. 3's 10 and 20):

1. the null: ``mapmerge.exhaustive.max_log_lr`` on unrelated pairs of the
   tuning seeds 300000+k (``--null-pairs`` of them, by default as many as
   ``--trials``). With at least ``EMPIRICAL_EXCEEDANCES / FALSE_ALARM``
   null pairs (10,000 at 1e-3) the threshold is the null's empirical upper
   ``FALSE_ALARM`` quantile (``--false-alarm``). With fewer it is
   extrapolated: the statistic is a maximum, so its upper tail is
   exponential (Gumbel's domain of attraction): above the null's
   ``TAIL_QUANTILE`` quantile u, the exceedances are fitted with an
   exponential law of mean β, and the threshold at a false-alarm rate
   ``FALSE_ALARM`` per pair is ``u + β log((1 - TAIL_QUANTILE) / FALSE_ALARM)``
   (peaks over threshold). On small maps ``--maximiser pairs`` seeks the
   same statistic's maximum from every two-landmark correspondence
   (``pair_max_log_lr``) instead of the grid: tens of times faster at 25-30
   dB, and higher than the grid's on many null pairs, whose chance maxima
   fall between its cells;
2. related pairs on seeds 100000+k (disjoint from the tuning seeds): the
   detector merges when the statistic passes the threshold, and the pair
   counts as found when it also put the transform within 1° and σ
   (``mapmerge.metrics.transform_found``); ``ml_accurate_rate`` counts the
   pairs whose ML transform is within 1° and σ whatever the statistic (no
   threshold at all, so no false-merge guarantee: an upper reference);
3. on the same pairs, ``consensus`` (``mapmerge.merge_maps`` with
   ``method="consensus"``, its other defaults and the same σ, but not the
   layout's prior): its two acceptance
   tests' statistics (``consensus_outcome``; the table ``stages``: where its
   power goes, and what each test's statistic would find at its own
   empirical null quantile), whether it merged,
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
import contextlib
import functools
import hashlib
import itertools
import json
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

import mapmerge as mm
from mapmerge.alignment import align_pairs, rotate
from mapmerge.association import SHARED_RANGE
from mapmerge.exhaustive import EXACT_RADIUS, Mixture, bump_height, pair_noise
from mapmerge.neighbours import njit

from .aggregate import ratio, save_table
from .trials import arithmetic_digest, code_digest, library_versions

SNRS = tuple(np.arange(0.0, 17.51, 2.5))
LAYOUTS = ("strip", "interleaved")
#: False alarms per unrelated pair allowed to the detector, as for the matchers' targets.
FALSE_ALARM = 1e-3
#: The null's exponential tail is fitted above this quantile.
TAIL_QUANTILE = 0.75
TUNING_SEED, REPORTED_SEED = 300_000, 100_000


#: ``pair_max_log_lr``: a p landmark pair seeds a transform with a q pair whose length differs by at most
#: this many standard deviations of the difference (2σ: two distances of two noisy landmarks each).
PAIR_GATE = 4.0
#: ``pair_max_log_lr``: seeds refined by EM (the best by their Λ, at distinct EM results).
PAIR_REFINE = 32
#: How the statistic's maximum over (θ, t) is sought: the grid of ``mapmerge.exhaustive.max_log_lr``, or
#: every transform that puts two q landmarks onto two p landmarks (``pair_max_log_lr``, small maps).
MAXIMISERS = ("grid", "pairs")


#: Landmarks per map unless ``--landmarks`` says otherwise (the paper's Fig. 1 scenario).
LANDMARKS = 100


def _pairs(n: int, layout: str, snr: float, seed: int, unrelated: bool):
    return mm.simulate.make_pairs(n, 0.75, snr, [seed], unrelated=unrelated, layout=layout)


def _pair(n: int, layout: str, snr: float, seed: int, unrelated: bool):
    return _pairs(n, layout, snr, seed, unrelated)[0]


@njit(cache=True)
def _seed_log_lr(Q, theta, t, equations, P, s, c, log_miss):
    """Λ (``Mixture.log_lr``: p landmarks within ``EXACT_RADIUS`` s) at each of many transforms of small maps."""
    out = np.empty(theta.shape[0])
    two_s2, r2 = 2 * s * s, (EXACT_RADIUS * s) ** 2
    for h in range(theta.shape[0]):
        co, si = np.cos(theta[h]), np.sin(theta[h])
        total = 0.0
        for k in range(Q.shape[0]):
            dx, dy = Q[k, 0] - t[h, 0], Q[k, 1] - t[h, 1]
            u, v = co * dx + si * dy, co * dy - si * dx
            inside = True
            for f in range(equations.shape[0]):
                if equations[f, 0] * u + equations[f, 1] * v + equations[f, 2] > 0:
                    inside = False
                    break
            if inside:
                bump = 0.0
                for i in range(P.shape[0]):
                    d2 = (u - P[i, 0]) ** 2 + (v - P[i, 1]) ** 2
                    if d2 <= r2:
                        bump += np.exp(-d2 / two_s2)
                total += log_miss + np.log1p(c * bump)
        out[h] = total
    return out


def pair_max_log_lr(P, Q, sigma: float, p_shared: float, density: float):
    """The detector's statistic, max over (θ, t) of Λ, sought from every two-landmark correspondence.

    A high Λ needs at least two q landmarks within a few s of p landmarks
    (one alone leaves the rotation free), so its maxima lie near the
    transforms that put a q landmark pair exactly onto a p landmark pair
    of about the same length. Every such transform is scored by Λ, and the
    ``PAIR_REFINE`` best are refined by EM (``Mixture.em``) and scored
    again. On small maps this costs O(n_p² n_q²) against the grid's
    O(n_θ · cells), and it finds a Λ at least as high as
    ``mapmerge.exhaustive.max_log_lr``'s on almost every pair (the grid's
    cells miss chance maxima); on large maps the seeds are too many.

    Parameters
    ----------
    P, Q : (n_p, 2), (n_q, 2) ndarray
        The two maps, at least 2 landmarks each.
    sigma, p_shared, density : float
        As for ``mapmerge.exhaustive.max_log_lr``.

    Returns
    -------
    log_lr : float
    theta : float
    t : (2,) ndarray
        Where the maximum was found: ``q ≈ R(θ) p + t`` (-inf, 0 and the origin when no seed exists).
    """
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    if P.ndim != 2 or Q.ndim != 2 or P.shape[1] != 2 or Q.shape[1] != 2 or min(len(P), len(Q)) < 2:
        raise ValueError(f"P and Q must be (n, 2) arrays of at least 2 landmarks, got {P.shape} and {Q.shape}")
    s = np.sqrt(2.0) * sigma
    model = Mixture.of_map(P, s, bump_height(density, 1.0, s, p_shared), p_shared)
    i, k = np.triu_indices(len(P), 1)
    j, l = np.nonzero(~np.eye(len(Q), dtype=bool))  # ordered: q's pair may map either way round
    vp, vq = P[k] - P[i], Q[l] - Q[j]
    a, b = np.nonzero(np.abs(np.hypot(*vp.T)[:, None] - np.hypot(*vq.T)[None]) <= PAIR_GATE * 2 * sigma)
    theta = np.arctan2(vq[b, 1], vq[b, 0]) - np.arctan2(vp[a, 1], vp[a, 0])
    t = 0.5 * (Q[j[b]] + Q[l[b]]) - rotate(theta, 0.5 * (P[i[a]] + P[k[a]])[:, None, :])[:, 0]
    value = _seed_log_lr(Q, theta, t, model.hull.equations, P, s, model.c, np.log(1 - p_shared))
    best, refined = (-np.inf, 0.0, np.zeros(2)), set()
    for h in np.argsort(-value, kind="stable"):
        if len(refined) >= PAIR_REFINE:
            break
        th, tt = model.em(Q, theta[h], t[h])
        # Seeds of one configuration converge to one transform: count distinct ones only.
        key = (round(float(np.mod(th, 2 * np.pi)), 6), round(float(tt[0]) / s, 3), round(float(tt[1]) / s, 3))
        if key in refined:
            continue
        refined.add(key)
        value_h = model.log_lr(Q, th, tt)[0]
        if value_h > best[0]:
            best = (value_h, th, tt)
    return best


def _statistic(maximiser, n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[float, bool, float]:
    sc = _pair(n, layout, snr, seed, unrelated)
    clock = time.perf_counter()
    value, theta, t = maximiser(sc.p, sc.q, sc.sigma, float(np.clip(sc.p_shared, *SHARED_RANGE)), sc.density)
    seconds = time.perf_counter() - clock
    return value, (not unrelated) and mm.metrics.transform_found(sc, theta, t), seconds


def statistic(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[float, bool, float]:
    """(max Λ, transform found, seconds) of one pair, on ``max_log_lr``'s grid."""
    return _statistic(mm.exhaustive.max_log_lr, n, layout, snr, seed, unrelated)


def pair_statistic(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple[float, bool, float]:
    """(max Λ, transform found, seconds) of one pair, by ``pair_max_log_lr``."""
    return _statistic(pair_max_log_lr, n, layout, snr, seed, unrelated)


@contextlib.contextmanager
def recorded_tests(search: bool = True):
    """Record consensus's two acceptance tests during ``merge_maps`` or ``merge_batch`` calls.

    The merges return their decisions only; to see how far each stage was
    from accepting, ``consensus.match_nfa_batch`` and the fallback
    ``search.search_batch`` (both looked up at call time) are wrapped for
    the duration. Yields a dict from a map p's bytes to what its map pair's
    tests gave: ``"triangles"``: (NFA, hypotheses, associations, θ, t) of
    its last triangle test, ``"count"``: the same match's
    ``consensus.count_nfa_batch`` (recorded, not what decides), ``"search"``:
    the search's NFA. Without ``search`` the global search declines every
    pair, so that the triangle test alone decides.
    """
    seen, match_nfa_batch, search_batch = {}, mm.consensus.match_nfa_batch, mm.search.search_batch

    def recorded_match_nfa_batch(P, Q, theta, t, cov, trial, pairs, n_hypotheses, *args, **kwargs):
        nfa = match_nfa_batch(P, Q, theta, t, cov, trial, pairs, n_hypotheses, *args, **kwargs)
        by_count = mm.consensus.count_nfa_batch(P, Q, theta, t, cov, trial, pairs, n_hypotheses, *args, **kwargs)
        count = np.bincount(trial, minlength=len(P))
        for b, p in enumerate(P):
            tests = seen.setdefault(p.tobytes(), {})
            tests["triangles"] = (nfa[b], n_hypotheses[b], int(count[b]), theta[b], t[b])
            tests["count"] = by_count[b]
        return nfa

    def recorded_search_batch(P, *args, **kwargs):
        declined = (np.empty(0, dtype=np.intp), np.empty((0, 2), dtype=np.intp), np.empty(0, dtype=bool),
                    np.full(len(P), np.inf))
        out = search_batch(P, *args, **kwargs) if search else declined
        for b, p in enumerate(P):
            seen.setdefault(p.tobytes(), {})["search"] = out[3][b]
        return out

    mm.consensus.match_nfa_batch, mm.search.search_batch = recorded_match_nfa_batch, recorded_search_batch
    try:
        yield seen
    finally:
        mm.consensus.match_nfa_batch, mm.search.search_batch = match_nfa_batch, search_batch


def search_hypotheses(P, Q, sigma: float) -> float:
    """The hypothesis count H of the global search's test on maps of at most
    ``search.MAX_SEARCH_LANDMARKS`` landmarks: rotations of step r / R times
    translation cells r wide over both maps' reach (``search`` docstring)."""
    r = pair_noise(sigma)
    reach_p = np.sqrt(np.max(np.sum((P - P.mean(axis=0)) ** 2, axis=1)))
    reach_q = np.sqrt(np.max(np.sum((Q - Q.mean(axis=0)) ** 2, axis=1)))
    return float(np.ceil(2 * np.pi * reach_p / r) * np.ceil(2 * (reach_p + reach_q) / r) ** 2)


def _search_best(sc) -> tuple[float, bool]:
    """The search's NFA, and whether its best hypothesis is the true transform, whatever the NFA."""
    with mock.patch.object(mm.search, "SEARCH_NFA", np.inf):
        pairs, _, nfa = mm.search.search_pairs(sc.p, sc.q, sc.sigma)
    if len(pairs) < 3:
        return nfa, False
    al = align_pairs(sc.p[pairs[:, 0]], sc.q[pairs[:, 1]], sc.sigma)
    return nfa, mm.metrics.transform_found(sc, al.theta, al.t)


def consensus_outcome(n: int, layout: str, snr: float, seed: int, unrelated: bool) -> tuple:
    """``consensus`` on the same pair: (merged, transform found, correct pairs, wrong pairs), then its stages.

    The stages: the triangle test's log NFA (inf when the triangles gave no
    consistent group of 3 associations), its hypothesis count and
    associations, whether its transform is the true one; the search's log
    NFA (inf when it declined or found nothing to refine), its hypothesis
    count H and the Chernoff bound log P(Λ >= observed) = log NFA - log H,
    whether its best hypothesis is the true transform. The search is
    measured even where the triangles accepted (it does not run then).
    """
    sc = _pair(n, layout, snr, seed, unrelated)
    with recorded_tests() as seen:
        err = mm.metrics.map_errors(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus"))
    tests = seen.get(sc.p.tobytes(), {})
    # inf, not NaN, for "no test made": pairs.csv drops NaN, so a NaN measure would be computed again on resume.
    tri_nfa, tri_hyp, tri_pairs, theta, t = tests.get("triangles", (np.inf, 0, 0, None, None))
    tri_found = theta is not None and not unrelated and mm.metrics.transform_found(sc, theta, t)
    if unrelated and "search" in tests:
        search_nfa, search_found = tests["search"], False
    else:
        search_nfa, search_found = _search_best(sc)
    log_h = np.log(search_hypotheses(sc.p, sc.q, sc.sigma))
    with np.errstate(divide="ignore"):
        log_search = float(np.log(search_nfa))
    return (err["matched"], err["matched"] and not unrelated and err["transform_found"], err["correct_pairs"],
            err["wrong_pairs"], float(np.log(tri_nfa)), tri_hyp, tri_pairs, tri_found, log_search, float(log_h),
            log_search - log_h, search_found)


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
            (pair_statistic, ("pair_log_lr", "pair_found", "pair_seconds")),
            (consensus_outcome, ("consensus_merged", "consensus_found", "consensus_correct", "consensus_wrong",
                                 "tri_log_nfa", "tri_hypotheses", "tri_pairs", "tri_found", "search_log_nfa",
                                 "search_log_hypotheses", "search_log_tail", "search_found")),
            (oracle_outcome, ("oracle_correct", "oracle_wrong", "transform_oracle_correct", "transform_oracle_wrong")),
            (correspondence_outcome, ("correspondence_found",)))


#: Null pairs per expected false alarm from which the threshold is the null's empirical quantile
#: rather than the tail fit's extrapolation (10,000 pairs at 1e-3).
EMPIRICAL_EXCEEDANCES = 10


def null_threshold(null: np.ndarray, false_alarm: float = FALSE_ALARM) -> tuple[float, str]:
    """Threshold at ``false_alarm`` per pair from null statistics, and how it was set.

    With at least ``EMPIRICAL_EXCEEDANCES / false_alarm`` null pairs, the
    empirical upper quantile ("empirical"): a statistic strictly above it
    is detected, which at most ``false_alarm`` of the null pairs are.
    With fewer, an exponential tail above their ``TAIL_QUANTILE`` ("tail").
    """
    null = np.asarray(null, float)
    if len(null) * false_alarm >= EMPIRICAL_EXCEEDANCES:
        return float(np.quantile(null, 1 - false_alarm, method="higher")), "empirical"
    u = float(np.quantile(null, TAIL_QUANTILE))
    beta = float(np.mean(null[null > u] - u))
    return u + beta * np.log((1 - TAIL_QUANTILE) / false_alarm), "tail"


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


def cell_jobs(n: int, layout: str, snr: float, trials: int, null_pairs: int | None = None) -> list[tuple]:
    """The null pairs (tuning seeds; ``null_pairs``, by default ``trials``), then the related pairs
    (reported seeds), of one cell."""
    counts = ((True, TUNING_SEED, trials if null_pairs is None else null_pairs), (False, REPORTED_SEED, trials))
    return [(int(n), layout, float(snr), int(seed), unrelated)
            for unrelated, base, count in counts for seed in base + np.arange(count)]


def _read(path: Path) -> pd.DataFrame:
    table = pd.read_csv(path)
    if "n_landmarks" not in table:  # written before maps of other sizes were measured
        table.insert(0, "n_landmarks", LANDMARKS)
    return table


def run_pairs(trials: int, n_jobs: int, path: Path, snrs=SNRS, layouts=LAYOUTS, landmarks=(LANDMARKS,),
              null_pairs: int | None = None, maximiser: str = "grid") -> pd.DataFrame:
    """Every measure of every null and related pair: one row each, in job order.

    ``maximiser`` ("grid" or "pairs") picks the detector's statistic measured
    (``statistic`` or ``pair_statistic``); the other is not computed.

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
        cell = cell_jobs(n, layout, snr, trials, null_pairs)
        changed = False
        for measure, columns in MEASURES:
            if measure is (pair_statistic if maximiser == "grid" else statistic):
                continue
            todo = [job for job in cell if not set(columns) <= known.get(job, {}).keys()]
            out = Parallel(n_jobs=n_jobs, batch_size=4)(delayed(measure)(*job) for job in todo)
            for job, values in zip(todo, out):
                known.setdefault(job, {CODE: code_key()}).update(zip(columns, values))
            changed |= bool(todo)
            print(f"{n} landmarks, {layout}, {snr:g} dB: {measure.__name__} on {len(todo)} pairs", flush=True)
        jobs += cell
        if changed:
            rows = {**other, **known}
            listed = set(jobs)
            order = jobs + [job for job in rows if job not in listed]
            table = pd.DataFrame([{**dict(zip(JOB, job)), **rows[job]} for job in order], columns=COLUMNS)
            table.to_csv(path, index=False, float_format="%.10g")  # seconds: its one machine-dependent column
    # The table is built from the file's values, so a resumed run gives the same table as a fresh one.
    return read_pairs(path, jobs)


def read_pairs(path: Path, jobs: list[tuple]) -> pd.DataFrame:
    """The rows of ``pairs.csv`` of these jobs, in their order (NaN where a job has none)."""
    return pd.DataFrame(jobs, columns=JOB).merge(_read(path), on=JOB, how="left", validate="one_to_one")


def limit_table(runs: pd.DataFrame, false_alarm: float = FALSE_ALARM, maximiser: str = "grid") -> pd.DataFrame:
    """Per cell: the detector at its null threshold for ``false_alarm``, and consensus on the same pairs."""
    prefix = "" if maximiser == "grid" else "pair_"
    rows = []
    for (n, layout, snr), g in runs.groupby(["n_landmarks", "layout", "snr_db"], sort=False):
        null, related = g[g.unrelated][f"{prefix}log_lr"].to_numpy(), g[~g.unrelated]
        found = related[related.consensus_found.astype(bool)]
        threshold, rule = null_threshold(null, false_alarm)
        # Strictly above: an empirical quantile is itself a null value.
        detected = related[f"{prefix}log_lr"].to_numpy() > threshold
        ml_found = related[f"{prefix}found"].astype(bool).to_numpy()
        rows.append({"n_landmarks": n, "layout": layout, "snr_db": snr, "maximiser": maximiser,
                     "false_alarm": false_alarm, "null_pairs": len(null), "null_max": null.max(),
                     "threshold": threshold, "threshold_rule": rule, "null_above": int(np.sum(null > threshold)),
                     "related_pairs": len(related),
                     "detected_rate": detected.mean(), "found_rate": (detected & ml_found).mean(),
                     # The ML transform's accuracy whatever its statistic: what no threshold could improve.
                     "ml_accurate_rate": ml_found.mean(),
                     # Knowing every correspondence: the accuracy no matcher is expected to beat.
                     "correspondence_found_rate": related.correspondence_found.astype(bool).mean(),
                     "consensus_found_rate": related.consensus_found.mean(),
                     "consensus_false_merges": int(g[g.unrelated].consensus_merged.sum()),
                     # Association where consensus found the transform, against both oracles' on those pairs.
                     **{f"consensus_{kind}_vs_{name}": float(ratio(found[f"consensus_{kind}"].sum(),
                                                                  found[f"{name}_{kind}"].sum()))
                        for name in ("oracle", "transform_oracle") for kind in ("correct", "wrong")},
                     "median_related_log_lr": float(np.median(related[f"{prefix}log_lr"])),
                     "median_s": float(np.median(g[f"{prefix}seconds"]))})
    return pd.DataFrame(rows)


#: Statistics of consensus's stages (``consensus_outcome``'s columns; lower is more significant), each
#: with the column saying whether the transform it would accept is the true one.
STAGE_STATISTICS = {"tri_log_nfa": "tri_found", "search_log_nfa": "search_found", "search_log_tail": "search_found"}


def stage_table(runs: pd.DataFrame, false_alarm: float = FALSE_ALARM) -> pd.DataFrame:
    """Per cell: where consensus's power goes on the null and related pairs, and what each stage's
    statistic would find at its own empirical null quantile for ``false_alarm``.

    ``combined`` is the rule "the triangles' transform if their log NFA passes
    its threshold, else the search's if its log NFA passes its own", the
    two thresholds set together so that at most ``false_alarm`` of the null
    pairs pass either (the same split of the budget as the defaults': the
    triangles' threshold at the null's ``false_alarm / 2`` quantile, the
    search's at the quantile that brings the union to ``false_alarm``).
    """
    rows = []
    for (n, layout, snr), g in runs.groupby(["n_landmarks", "layout", "snr_db"], sort=False):
        null, related = g[g.unrelated], g[~g.unrelated]
        row = {"n_landmarks": n, "layout": layout, "snr_db": snr, "null_pairs": len(null),
               "related_pairs": len(related), "false_alarm": false_alarm,
               "consensus_found_rate": related.consensus_found.astype(bool).mean(),
               "consensus_false_merges": int(null.consensus_merged.astype(bool).sum())}
        for name, part in (("null", null), ("related", related)):
            group = np.isfinite(part.tri_log_nfa)
            row[f"{name}_tri_group_rate"] = group.mean()
            row[f"{name}_median_tri_log_nfa"] = float(np.median(part.tri_log_nfa[group])) if group.any() else np.nan
            row[f"{name}_median_tri_log_hypotheses"] = (float(np.median(np.log(part.tri_hypotheses[group])))
                                                        if group.any() else np.nan)
            ran = np.isfinite(part.search_log_nfa)
            row[f"{name}_median_search_log_nfa"] = float(np.median(part.search_log_nfa[ran])) if ran.any() else np.nan
            row[f"{name}_median_search_log_hypotheses"] = float(np.median(part.search_log_hypotheses))
            row[f"{name}_median_search_log_tail"] = float(np.median(part.search_log_tail[ran])) if ran.any() else np.nan
        row["related_tri_found_rate"] = related.tri_found.astype(bool).mean()
        row["related_search_best_found_rate"] = related.search_found.astype(bool).mean()
        for stat, found in STAGE_STATISTICS.items():
            threshold = float(np.quantile(null[stat], false_alarm, method="lower"))
            row[f"{stat}_threshold"] = threshold
            row[f"{stat}_null_pass"] = int(np.sum(null[stat] < threshold))
            row[f"{stat}_found_rate"] = float(np.mean((related[stat] < threshold) & related[found].astype(bool)))
        tri_t = float(np.quantile(null.tri_log_nfa, false_alarm / 2, method="lower"))
        rest = null.tri_log_nfa >= tri_t
        # The search's threshold: the largest that keeps the union's null passes within the budget.
        budget = int(np.floor(false_alarm * len(null))) - int(np.sum(~rest))
        values = np.sort(null.search_log_nfa[rest].to_numpy())
        search_t = float(values[budget]) if 0 <= budget < len(values) else -np.inf
        tri_pass = related.tri_log_nfa < tri_t
        search_pass = ~tri_pass & (related.search_log_nfa < search_t)
        row.update({"combined_tri_threshold": tri_t, "combined_search_threshold": search_t,
                    "combined_null_pass": int(np.sum(~rest) + np.sum(null.search_log_nfa[rest] < search_t)),
                    "combined_found_rate": float(np.mean(tri_pass & related.tri_found.astype(bool)
                                                         | search_pass & related.search_found.astype(bool)))})
        rows.append(row)
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="The exhaustive ML detector's limit curve.")
    parser.add_argument("--trials", type=int, default=100, help="pairs per cell, null and related each")
    parser.add_argument("--null-pairs", type=int, default=None,
                        help="unrelated (tuning) pairs per cell, if not --trials")
    parser.add_argument("--false-alarm", type=float, default=FALSE_ALARM,
                        help=f"false alarms per unrelated pair the threshold allows (default {FALSE_ALARM:g}); "
                             f"with >= {EMPIRICAL_EXCEEDANCES} / it null pairs, the null's empirical quantile")
    parser.add_argument("--tables-only", action="store_true",
                        help="rebuild the tables from pairs.csv's rows, whatever code wrote them; compute nothing")
    parser.add_argument("--maximiser", choices=MAXIMISERS, default="grid",
                        help="how max Λ is sought: max_log_lr's grid, or every two-landmark correspondence "
                             "(small maps only)")
    parser.add_argument("--out", default="results/detector")
    parser.add_argument("--n-jobs", type=int, default=2)
    parser.add_argument("--snrs", type=float, nargs="+", default=SNRS, help="SNRs in dB (default: 0-17.5 by 2.5)")
    parser.add_argument("--layouts", nargs="+", choices=LAYOUTS, default=LAYOUTS)
    parser.add_argument("--landmarks", type=int, nargs="+", default=[LANDMARKS],
                        help=f"landmarks per map (default: {LANDMARKS})")
    args = parser.parse_args(argv)
    if args.trials < 8 or (args.null_pairs is not None and args.null_pairs < 8):
        raise SystemExit("--trials and --null-pairs must be >= 8 (the null's tail fit needs them)")
    if not 0 < args.false_alarm < 1:
        raise SystemExit(f"--false-alarm must lie in (0, 1), got {args.false_alarm!r}")
    for n, snr in itertools.product(args.landmarks, args.snrs):
        try:
            mm.simulate.check_scenario(n, 0.75, snr, 1.0)
        except mm.simulate.ScenarioError as exc:
            # The overlap is fixed here: an overlap too small for 3 common landmarks means too few landmarks.
            flag, value = ("snrs", snr) if exc.argument == "snr_db" else ("landmarks", n)
            raise SystemExit(f"--{flag} {value!r}: {exc.rule}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.tables_only:
        runs = read_pairs(out / "pairs.csv", [job for n, layout, snr in itertools.product(
            args.landmarks, args.layouts, args.snrs) for job in cell_jobs(n, layout, snr, args.trials, args.null_pairs)])
        if runs.code.isna().any():
            raise SystemExit(f"--tables-only: {int(runs.code.isna().sum())} of the pairs asked for are not in "
                             f"{out / 'pairs.csv'}")
    else:
        runs = run_pairs(args.trials, args.n_jobs, out / "pairs.csv", args.snrs, args.layouts, args.landmarks,
                         args.null_pairs, args.maximiser)
    for path in save_table(limit_table(runs, args.false_alarm, args.maximiser), out / "limit"):
        print(path)
    for path in save_table(stage_table(runs, args.false_alarm), out / "stages"):
        print(path)


if __name__ == "__main__":
    main()
