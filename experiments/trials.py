"""Monte Carlo trials of one grid cell: seeding and one chunk of trials.

Nothing here knows about Hydra: a cell is a plain dict of scientific
parameters and a matcher dict, so the code runs the same in a joblib worker,
a dask worker or a test. Every stage is the library's, run on the whole
chunk at once (``mapmerge.simulate.make_pairs``, ``mapmerge.merging``,
``mapmerge.metrics``); per trial only its random stream, its Delaunay calls
and its LP run alone.

Seeding: trial k of cell c draws from
``SeedSequence(root_seed, spawn_key=(cell_key(c), k))``, so any trial can be
recomputed alone and the results do not depend on workers or chunking. The
cell key hashes the *scenario* only, so every matcher sees the same maps.
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
from mapmerge.datasets import victoria_park
from mapmerge.merging import get_method, match_stage, merge_at
from mapmerge.search import SearchMemo
from mapmerge.simulate import ScenarioBatch, check_scenario

SCENARIO_KEYS = ("n_landmarks", "overlap", "snr_db", "aspect", "unrelated", "layout", "p_detect", "clutter",
                 "anisotropy")
#: Scenario keys added after the first release, with the value that gives
#: the first release's maps: left out of the cell key at that value, so
#: existing cells keep their seeds.
LATER_KEYS = {"layout": "strip", "p_detect": 0.9, "clutter": 0.0, "anisotropy": 0.0}
#: Keys of a real-data scenario (``kind: victoria_park``).
DATASET_KEYS = ("cut", "source")

#: Columns whose values depend on the machine's speed, kept out of the
#: bit-identical result files.
TIME_COLUMNS = ("time_match_s", "time_merge_s")
#: Triangle pairs scored at once (about 32 MB per array of scores): a chunk
#: of big maps runs in slices of trials that fit.
MAX_PAIRS = 2**22


@functools.cache
def code_digest(module: str = __file__) -> str:
    """Digest of the sources that compute results: the library and ``module`` (by default this
    one, whose trials the harness's chunk cache holds)."""
    files = sorted(Path(mm.__file__).resolve().parent.rglob("*.py")) + [Path(module).resolve()]
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.read_bytes())
    return digest.hexdigest()


def library_versions() -> dict[str, str]:
    """numpy's and scipy's versions: part of the cache keys, since another release of either may
    give other bits (a Delaunay triangulation, a random stream, a transcendental function)."""
    import scipy

    return {"numpy": np.__version__, "scipy": scipy.__version__}


@functools.cache
def arithmetic_digest() -> str:
    """Digest of numpy's sin, cos, exp, log and arctan2 on fixed inputs: part of the harness's
    chunk-cache key. numpy's AVX-512 kernels and the C library's differ in the last bit of some
    results, which can relabel a trial, so machines that compute these differently have
    different digests and never reuse each other's chunks."""
    x = np.random.default_rng(0).uniform(-20.0, 20.0, 4096)
    digest = hashlib.sha256()
    for values in (np.sin(x), np.cos(x), np.exp(x), np.log(np.abs(x)), np.arctan2(x, x[::-1])):
        digest.update(values.tobytes())
    return digest.hexdigest()


def is_dataset(scenario: dict) -> bool:
    return scenario.get("kind", "synthetic") == "victoria_park"


def scientific_keys(scenario: dict) -> tuple[str, ...]:
    return DATASET_KEYS if is_dataset(scenario) else SCENARIO_KEYS


def cell_key(scenario: dict) -> int:
    """Stable 63-bit key of a scenario's scientific parameters."""
    scenario = {**LATER_KEYS, **scenario}
    keys = [k for k in scientific_keys(scenario) if k not in LATER_KEYS or scenario[k] != LATER_KEYS[k]]
    canon = json.dumps({k: scenario[k] if isinstance(scenario[k], str) else float(scenario[k]) for k in keys},
                       sort_keys=True)
    return int.from_bytes(hashlib.sha256(canon.encode()).digest()[:8], "big") >> 1


def trial_seeds(root_seed: int, scenario: dict, ks) -> mm.simulate.SpawnedSeeds:
    return mm.simulate.SpawnedSeeds(int(root_seed), (cell_key(scenario),), np.asarray(ks, dtype=np.int64))


@functools.lru_cache(maxsize=8)
def _victoria_park(cut: int, source: str):
    return victoria_park(cut=cut, source=source)


def make_trials(root_seed: int, scenario: dict, ks):
    """The map pairs of trials ``ks`` as a ``ScenarioBatch`` (a data set is its one fixed pair)."""
    if is_dataset(scenario):
        sc = _victoria_park(int(scenario["cut"]), str(scenario["source"]))
        batch = ScenarioBatch(sc.p[None], sc.q[None], sc.ids_p[None], sc.ids_q[None], sc.truth[None],
                              np.array([sc.sigma]), np.array([sc.theta]), sc.t[None], np.nan, np.array([np.nan]),
                              np.array([sc.n_common]), sc.cov_p[None], sc.cov_q[None], np.nan, np.nan)
        return batch, sc
    scenario = {**LATER_KEYS, **scenario}
    batch = mm.simulate.make_pairs(int(scenario["n_landmarks"]), float(scenario["overlap"]),
                                   float(scenario["snr_db"]), trial_seeds(root_seed, scenario, ks),
                                   aspect=float(scenario["aspect"]), unrelated=bool(scenario["unrelated"]),
                                   layout=str(scenario["layout"]), p_detect=float(scenario["p_detect"]),
                                   clutter=float(scenario["clutter"]), anisotropy=float(scenario["anisotropy"]))
    return batch, None


def _loosest_tau(taus) -> float | None:
    """The loosest fixed rule (it gates the sparse large-map path); None with the oracle rule."""
    if "oracle" in taus or "none" in taus:
        return None
    return min(mm.resolve_log_tau(rule) for rule in taus)


def _slice_size(scenario: dict) -> int:
    if is_dataset(scenario):
        return 1
    n, _ = check_scenario(scenario["n_landmarks"], scenario["overlap"], scenario["snr_db"], scenario["aspect"])
    n += int(np.ceil(n * float(scenario.get("clutter", 0.0))))
    # At most 2n - 5 triangles per map; trials are independent, so slicing
    # changes nothing but memory.
    return max(1, MAX_PAIRS // max(2 * n - 5, 1) ** 2)


def run_chunk(root_seed: int, scenario: dict, matcher: dict, start: int, stop: int):
    """Trials ``start..stop-1`` of a cell as (trials, pairs) DataFrames.

    ``trials``: one row per trial and τ rule (``"none"`` for methods without
    a threshold): detection counts, map-level errors, timings (the time per
    trial of the slice of trials run together). ``pairs``: one row per
    tentative triangle pair of the triangle-LP methods (τ-independent).
    """
    per_slice = _slice_size(scenario)
    parts = [_run_slice(root_seed, scenario, matcher, np.arange(a, min(a + per_slice, stop)))
             for a in range(start, stop, per_slice)]
    if len(parts) == 1:
        return parts[0]
    return tuple(pd.concat([p[k] for p in parts], ignore_index=True) for k in (0, 1))


def matcher_covariances(sc, matcher: dict) -> dict:
    """The landmarks' covariances as ``merge_at`` keywords when the matcher uses them (``use_cov``)."""
    return {"cov_p": sc.cov_p, "cov_q": sc.cov_q} if matcher.get("use_cov") else {}


def _run_slice(root_seed: int, scenario: dict, matcher: dict, ks: np.ndarray):
    sc, dataset = make_trials(root_seed, scenario, ks)
    B = len(sc)
    method = get_method(matcher["method"])
    taus = list(matcher["taus"]) if method.uses_tau else ["none"]
    covariances = matcher_covariances(sc, matcher)
    first_pose = None if dataset is None else (dataset.theta_first_pose, dataset.t_first_pose[None])
    oracle = metrics.oracle_pairs_batch(sc) if matcher.get("oracle") and dataset is None else {}

    clock = time.perf_counter()
    match = match_stage(sc.p, sc.q, sc.sigma, method.name, matcher.get("objective", "lr"), _loosest_tau(taus))
    time_match = (time.perf_counter() - clock) / B
    lp_true = lp_consistent = None
    if match is not None:
        lp_true, lp_consistent = pair_labels(sc, match.tri_p, match.tri_q, match.trial, match.triangle_pairs)
    # Baselines (no match stage) count common triangles from their own merge's triangles.
    n_common = None if match is None else metrics.common_triangle_counts(sc.ids_p, sc.ids_q, match.tri_p,
                                                                         match.tri_q)
    columns, last = [], None
    # The rules' merges of the same maps share consensus's global searches (τ-independent).
    memo = SearchMemo()
    for rule in taus:
        clock = time.perf_counter()
        log_tau = rule_log_tau(rule, match, lp_true, B)
        declared = None if match is None else match.log_lr >= log_tau[match.trial]
        if last is None:
            row = _evaluate(sc, match, log_tau, method.name, covariances, n_common, lp_true, lp_consistent, first_pose,
                            memo)
        else:
            # A trial whose declared pairs did not change merges as under the previous rule.
            row = {key: value.copy() for key, value in last[1].items()}
            sub = np.flatnonzero(np.bincount(match.trial[declared != last[0]], minlength=B))
            if sub.size:
                part = _evaluate(sc.take(sub), match.take(sub), log_tau[sub], method.name,
                                 {k: v[sub] for k, v in covariances.items()}, n_common[sub],
                                 lp_true[np.isin(match.trial, sub)], lp_consistent[np.isin(match.trial, sub)],
                                 first_pose, memo)
                for key, value in part.items():
                    row[key][sub] = value
        last = declared, row
        columns.append({"trial": ks, "tau": np.full(B, rule, dtype=object), "log_tau": log_tau,
                        "sigma": sc.sigma, "n_p": np.full(B, sc.p.shape[1]), "n_q": np.full(B, sc.q.shape[1]),
                        "n_common_landmarks": sc.n_common, **row, **oracle,
                        "time_match_s": np.full(B, time_match),
                        "time_merge_s": np.full(B, (time.perf_counter() - clock) / B)})
    # Trial-major, rule-minor rows.
    trials = pd.DataFrame({key: np.stack([col[key] for col in columns], axis=1).ravel() for key in columns[0]})
    if match is None:
        pairs = pd.DataFrame({"trial": np.empty(0, np.int64), "score": np.empty(0), "label": np.empty(0, bool),
                              "order_consistent": np.empty(0, bool)})
    else:
        pairs = pd.DataFrame({"trial": ks[match.trial], "score": match.log_lr, "label": lp_true,
                              "order_consistent": lp_consistent})
    return trials, pairs


def _evaluate(sc, match, log_tau, method, covariances, n_common, lp_true, lp_consistent, first_pose=None,
              search_memo=None) -> dict:
    """Merge at log τ and score against the truth: detection counts and map errors per trial.

    ``first_pose`` (θ, t) of a real data set adds the errors against its
    second truth, the transform between the agents' first poses.
    """
    merged = merge_at(sc.p, sc.q, sc.sigma, match, log_tau, method=method, **covariances, search_memo=search_memo)
    if n_common is None:
        n_common = metrics.common_triangle_counts(sc.ids_p, sc.ids_q, merged.tri_p, merged.tri_q)
    if match is not None and merged.triangle_pairs is match.triangle_pairs:
        is_true, consistent = lp_true, lp_consistent  # the LP's own pairs: labelled once
    else:
        is_true, consistent = pair_labels(sc, merged.tri_p, merged.tri_q, merged.tri_trial, merged.triangle_pairs)
    # Consensus also declares triangles implied by its landmark association whose log Λ is below τ.
    with np.errstate(invalid="ignore"):
        implied = merged.declared & (merged.triangle_log_lr < log_tau[merged.tri_trial])
    row = {**metrics.detection_counts_batch(merged.tri_trial, is_true, merged.declared, n_common),
           "tp_implied": np.bincount(merged.tri_trial[is_true & implied], minlength=len(sc)),
           "order_flips": np.bincount(merged.tri_trial[is_true & ~consistent], minlength=len(sc)),
           **metrics.map_errors_batch(sc, merged)}
    if first_pose is not None:
        # The estimate itself too: on real maps its error against other truths is computed later.
        row["theta"], row["t_x"], row["t_y"] = merged.theta, merged.t[:, 0], merged.t[:, 1]
        row["rot_err_first_pose_deg"] = np.degrees(np.abs(mm.wrap_angle(merged.theta - first_pose[0])))
        row["trans_err_first_pose"] = np.sqrt(np.sum((merged.t - first_pose[1]) ** 2, axis=1))
    return row


def rule_log_tau(rule: str, match, lp_true, n_trials: int) -> np.ndarray:
    """log τ per trial of a τ rule: ``"oracle"`` (ground truth, zero false
    positives among the tentative pairs), ``"none"`` (NaN, methods without
    τ) or a library form (``"chi2:P"`` or a log-LR)."""
    if rule == "none":
        return np.full(n_trials, np.nan)
    if rule == "oracle":
        return metrics.oracle_log_tau_batch(match.trial, lp_true, match.log_lr, n_trials)
    return np.full(n_trials, mm.resolve_log_tau(rule))


def pair_labels(sc, tri_p, tri_q, trial, triangle_pairs):
    """Truth (is_true, order_consistent) of triangle pairs given by their indices within each map pair."""
    return metrics.triangle_labels_batch(
        sc.ids_p, sc.ids_q, trial, tri_p.vertices[tri_p.offsets[trial] + triangle_pairs[:, 0]],
        tri_q.vertices[tri_q.offsets[trial] + triangle_pairs[:, 1]])
