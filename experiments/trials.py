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

import hashlib
import json
import time

import numpy as np
import pandas as pd

import mapmerge as mm
from mapmerge import metrics
from mapmerge.merging import match_triangles, merge_at

SCENARIO_KEYS = ("n_landmarks", "overlap", "snr_db", "aspect")

#: Columns whose values depend on the machine's speed, kept out of the
#: bit-identical result files.
TIME_COLUMNS = ("time_match_s", "time_merge_s")


def cell_key(scenario: dict) -> int:
    """Stable 63-bit key of a scenario's scientific parameters."""
    canon = json.dumps({k: float(scenario[k]) for k in SCENARIO_KEYS}, sort_keys=True)
    return int.from_bytes(hashlib.sha256(canon.encode()).digest()[:8], "big") >> 1


def trial_seed(root_seed: int, scenario: dict, k: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(int(root_seed), spawn_key=(cell_key(scenario), int(k)))


def make_trial_pair(root_seed: int, scenario: dict, k: int) -> mm.simulate.Scenario:
    return mm.simulate.make_pair(
        n_landmarks=int(scenario["n_landmarks"]),
        overlap=float(scenario["overlap"]),
        snr_db=float(scenario["snr_db"]),
        rng=trial_seed(root_seed, scenario, k),
        aspect=float(scenario["aspect"]),
    )


def resolve_tau(rule: str, is_true: np.ndarray, scores: np.ndarray) -> float:
    """log τ for a rule: ``"oracle"`` (ground truth, zero FP) or a library form."""
    if rule == "oracle":
        return metrics.oracle_log_tau(is_true, scores)
    return mm.resolve_log_tau(rule)


def run_trial(root_seed: int, scenario: dict, matcher: dict, k: int):
    """One trial: draw the pair, match once, then evaluate every τ rule.

    Returns
    -------
    trial_rows : list of dict
        One row per τ rule: counts, map-level errors, timings.
    pairs : dict of arrays
        One entry per tentative triangle pair (τ-independent).
    """
    sc = make_trial_pair(root_seed, scenario, k)
    start = time.perf_counter()
    match = match_triangles(sc.p, sc.q, sc.sigma, matcher["objective"])
    time_match = time.perf_counter() - start
    vp, vq = match.tri_p.vertices, match.tri_q.vertices
    scores = match.triangle_log_lr
    is_true, consistent = metrics.triangle_labels(sc.ids_p, sc.ids_q, vp, vq, match.triangle_pairs)
    n_common = len(metrics.common_triangles(sc.ids_p, sc.ids_q, vp, vq))

    rows = []
    for rule in matcher["taus"]:
        start = time.perf_counter()
        log_tau = resolve_tau(rule, is_true, scores)
        res = merge_at(sc.p, sc.q, sc.sigma, match, log_tau)
        time_merge = time.perf_counter() - start
        row = {"trial": k, "tau": rule, "log_tau": log_tau, "sigma": sc.sigma}
        row.update(metrics.detection_counts(is_true, res.declared, n_common))
        row["order_flips"] = int(np.sum(is_true & ~consistent))
        row.update(metrics.map_errors(sc, res))
        row["time_match_s"] = time_match
        row["time_merge_s"] = time_merge
        rows.append(row)
    pairs = {
        "trial": np.full(scores.size, k, dtype=np.int64),
        "score": scores,
        "label": is_true,
        "order_consistent": consistent,
    }
    return rows, pairs


def run_chunk(root_seed: int, scenario: dict, matcher: dict, start: int, stop: int):
    """Trials ``start..stop-1`` of a cell as (trials, pairs) DataFrames."""
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
