"""Monte Carlo trials of one grid cell: seeding, one trial, one chunk.

Nothing here knows about Hydra: a cell is a plain dict of scientific
parameters and a matcher dict, so the code runs the same in a joblib worker,
a dask worker or a test.

Seeding (DESIGN §6): trial k of cell c draws from
``SeedSequence(root_seed, spawn_key=(cell_key(c), k))``, so any trial can be
recomputed alone and the results do not depend on workers or chunking.
The cell key hashes the *scenario* only, so every matcher sees the same maps.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

import mapmerge as mm
from mapmerge import metrics
from mapmerge.baselines import BASELINES
from mapmerge.datasets import victoria_park
from mapmerge.merging import match_triangles, merge_at

from . import batched

SCENARIO_KEYS = ("n_landmarks", "overlap", "snr_db", "aspect", "unrelated")
#: Keys of a real-data scenario (``kind: victoria_park``).
DATASET_KEYS = ("cut", "source")

#: Columns whose values depend on the machine's speed, kept out of the
#: bit-identical result files.
TIME_COLUMNS = ("time_match_s", "time_merge_s")


@functools.cache
def code_digest() -> str:
    """Digest of the sources that compute trials (the library and the two
    trial engines): part of the harness's chunk-cache key."""
    here = Path(__file__).resolve().parent
    files = sorted(Path(mm.__file__).resolve().parent.rglob("*.py")) + [here / "trials.py", here / "batched.py"]
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.read_bytes())
    return digest.hexdigest()


def scientific_keys(scenario: dict) -> tuple[str, ...]:
    return DATASET_KEYS if scenario.get("kind", "synthetic") == "victoria_park" else SCENARIO_KEYS


def cell_key(scenario: dict) -> int:
    """Stable 63-bit key of a scenario's scientific parameters."""
    canon = json.dumps({k: scenario[k] if isinstance(scenario[k], str) else float(scenario[k])
                        for k in scientific_keys(scenario)}, sort_keys=True)
    return int.from_bytes(hashlib.sha256(canon.encode()).digest()[:8], "big") >> 1


def trial_seed(root_seed: int, scenario: dict, k: int) -> np.random.SeedSequence:
    return trial_seeds(root_seed, scenario, [k])[0]


def trial_seeds(root_seed: int, scenario: dict, ks) -> list[np.random.SeedSequence]:
    key = cell_key(scenario)
    return [np.random.SeedSequence(int(root_seed), spawn_key=(key, int(k))) for k in ks]


@functools.lru_cache(maxsize=8)
def _victoria_park(cut: int, source: str):
    return victoria_park(cut=cut, source=source)


def make_trial_pair(root_seed: int, scenario: dict, k: int):
    """The map pair of trial k: synthetic (seeded) or the real data set."""
    if scenario.get("kind", "synthetic") == "victoria_park":
        return _victoria_park(int(scenario["cut"]), str(scenario["source"]))
    return mm.simulate.make_pair(
        n_landmarks=int(scenario["n_landmarks"]),
        overlap=float(scenario["overlap"]),
        snr_db=float(scenario["snr_db"]),
        rng=trial_seed(root_seed, scenario, k),
        aspect=float(scenario["aspect"]),
        unrelated=bool(scenario["unrelated"]),
    )


def resolve_tau(rule: str, is_true: np.ndarray, scores: np.ndarray) -> float:
    """log τ for a rule: ``"oracle"`` (ground truth, zero FP) or a library form."""
    if rule == "oracle":
        return metrics.oracle_log_tau(is_true, scores)
    return mm.resolve_log_tau(rule)


def merge_trial(sc, matcher: dict):
    """Run a matcher on one map pair for every τ rule, timing each stage.

    Returns
    -------
    match : TriangleMatch or None
        The LP's tentative pairs (None for baselines, which have no τ and
        give a single result under the rule ``"none"``).
    lp_labels : (is_true, order_consistent) of the tentative pairs, or None.
    results : list of (rule, MergeResult, time_merge_s)
    time_match : float
    """
    method = matcher["method"]
    start = time.perf_counter()
    if method in BASELINES:
        res = BASELINES[method](sc.p, sc.q, sc.sigma)
        return None, None, [("none", res, time.perf_counter() - start)], 0.0
    match = match_triangles(sc.p, sc.q, sc.sigma, matcher["objective"], cyclic=method != "paper")
    time_match = time.perf_counter() - start
    labels = metrics.triangle_labels(
        sc.ids_p, sc.ids_q, match.tri_p.vertices, match.tri_q.vertices, match.triangle_pairs
    )
    variances = {}
    if matcher.get("use_cov") and hasattr(sc, "cov_p"):
        variances = {"var_p": np.trace(sc.cov_p, axis1=1, axis2=2) / 2,
                     "var_q": np.trace(sc.cov_q, axis1=1, axis2=2) / 2}
    results = []
    for rule in matcher["taus"]:
        start = time.perf_counter()
        log_tau = resolve_tau(rule, labels[0], match.triangle_log_lr)
        res = merge_at(sc.p, sc.q, sc.sigma, match, log_tau, method, **variances)
        results.append((rule, res, time.perf_counter() - start))
    return match, labels, results, time_match


def run_trial(root_seed: int, scenario: dict, matcher: dict, k: int):
    """One trial: draw the pair, match once, then evaluate every τ rule.

    Returns
    -------
    trial_rows : list of dict
        One row per τ rule (``"none"`` for baselines): counts, map-level
        errors, timings.
    pairs : dict of arrays
        One entry per tentative triangle pair (τ-independent; empty for
        baselines).
    """
    sc = make_trial_pair(root_seed, scenario, k)
    match, labels, results, time_match = merge_trial(sc, matcher)
    tri_p, tri_q = results[0][1].tri_p, results[0][1].tri_q
    vp, vq = tri_p.vertices, tri_q.vertices
    n_common = len(metrics.common_triangles(sc.ids_p, sc.ids_q, vp, vq))
    rows = []
    for rule, res, time_merge in results:
        is_true, consistent = metrics.triangle_labels(sc.ids_p, sc.ids_q, vp, vq, res.triangle_pairs)
        row = {"trial": k, "tau": rule, "log_tau": res.log_tau, "sigma": sc.sigma,
               "n_p": len(sc.p), "n_q": len(sc.q), "n_common_landmarks": sc.n_common}
        row.update(metrics.detection_counts(is_true, res.declared, n_common))
        row["order_flips"] = int(np.sum(is_true & ~consistent))
        row.update(metrics.map_errors(sc, res))
        row["false_merge"] = bool(res.matched and sc.n_common == 0)
        row["time_match_s"] = time_match
        row["time_merge_s"] = time_merge
        rows.append(row)
    if match is None:
        pairs = {"trial": np.empty(0, np.int64), "score": np.empty(0), "label": np.empty(0, bool),
                 "order_consistent": np.empty(0, bool)}
    else:
        pairs = {
            "trial": np.full(match.triangle_log_lr.size, k, dtype=np.int64),
            "score": match.triangle_log_lr,
            "label": labels[0],
            "order_consistent": labels[1],
        }
    return rows, pairs


def run_chunk(root_seed: int, scenario: dict, matcher: dict, start: int, stop: int,
              batch: bool | None = None):
    """Trials ``start..stop-1`` of a cell as (trials, pairs) DataFrames.

    ``batch`` (default: whenever ``batched.supports`` the cell) runs the
    chunk on the batched engine, which gives the same results many times
    faster; ``batch=False`` forces the per-trial path.
    """
    if batch or (batch is None and batched.supports(scenario, matcher)):
        return batched.run_chunk(root_seed, scenario, matcher, start, stop)
    rows, pair_parts = [], []
    for k in range(start, stop):
        trial_rows, pairs = run_trial(root_seed, scenario, matcher, k)
        rows.extend(trial_rows)
        pair_parts.append(pairs)
    trials = pd.DataFrame(rows)
    pairs = pd.DataFrame(
        {col: np.concatenate([p[col] for p in pair_parts]) for col in pair_parts[0]}
    )
    return trials, pairs
