"""The batched trial engine against the per-trial reference path."""

import numpy as np
import pandas as pd
import pytest

from experiments import batched
from experiments.trials import run_chunk
from mapmerge.matching import correspondences

#: Map-level errors come from per-trial sums in another order: equal to rounding.
ROUNDED = ("rot_err_deg", "trans_err", "rmse")


def _scenario(n, overlap, snr_db, unrelated=False, aspect=1.0):
    return {"kind": "synthetic", "n_landmarks": n, "overlap": overlap, "snr_db": snr_db,
            "aspect": aspect, "unrelated": unrelated}


@pytest.mark.parametrize("scenario, method, objective", [
    (_scenario(10, 0.75, 20.0), "paper", "lr"),
    (_scenario(20, 0.5, 40.0, aspect=1.5), "cyclic", "lr"),
    (_scenario(20, 0.5, 0.0), "paper", "loglr"),
    (_scenario(12, 0.75, 30.0, unrelated=True), "paper", "lr"),
])
def test_batched_equals_per_trial(scenario, method, objective):
    matcher = {"method": method, "objective": objective, "taus": ["oracle", "chi2:0.01", "chi2:0.001"]}
    assert batched.supports(scenario, matcher)
    ref_trials, ref_pairs = run_chunk(3, scenario, matcher, 40, 160, batch=False)
    trials, pairs = run_chunk(3, scenario, matcher, 40, 160, batch=True)
    pd.testing.assert_frame_equal(pairs, ref_pairs)  # same tentative pairs and scores, bit for bit
    assert list(trials.columns) == list(ref_trials.columns)
    exact = [c for c in trials.columns if c not in ROUNDED and not c.startswith("time_")]
    pd.testing.assert_frame_equal(trials[exact], ref_trials[exact])
    for col in ROUNDED:
        np.testing.assert_allclose(trials[col], ref_trials[col], rtol=1e-9, atol=1e-12)
    # The cells exercise what they should: merges, detections only on related
    # maps, and conflicting correspondences at 0 dB.
    assert ref_trials.matched.any()
    assert (ref_trials.tp > 0).any() != scenario["unrelated"]
    assert (ref_trials.n_conflicts > 0).any() or scenario["snr_db"] > 0


def test_batched_does_not_depend_on_chunking():
    scenario = _scenario(15, 0.75, 10.0)
    matcher = {"method": "cyclic", "objective": "lr", "taus": ["oracle", "chi2:0.01"]}
    whole = run_chunk(0, scenario, matcher, 0, 90)
    parts = [run_chunk(0, scenario, matcher, a, b) for a, b in ((0, 1), (1, 37), (37, 90))]
    for k in (0, 1):
        joined = pd.concat([p[k] for p in parts], ignore_index=True)
        timeless = [c for c in whole[k].columns if not c.startswith("time_")]
        pd.testing.assert_frame_equal(whole[k][timeless], joined[timeless], check_exact=True)


def test_other_cells_stay_on_the_per_trial_path():
    assert not batched.supports(_scenario(10, 0.75, 20.0), {"method": "consensus"})
    assert not batched.supports({"kind": "victoria_park", "cut": 1, "source": "slam"}, {"method": "paper"})


def _sequential_greedy(vertices_p, vertices_q, log_lr):
    """The documented rule, one candidate at a time (most votes, best score, lowest indices)."""
    cand = {}
    for tp, tq, s in zip(vertices_p, vertices_q, log_lr):
        for i, j in zip(tp, tq):
            votes, best = cand.get((i, j), (0, -np.inf))
            cand[(i, j)] = (votes + 1, max(best, s))
    used_p, used_q, keep = set(), set(), []
    for (i, j), _ in sorted(cand.items(), key=lambda kv: (-kv[1][0], -kv[1][1], kv[0][0], kv[0][1])):
        if i not in used_p and j not in used_q:
            used_p.add(i), used_q.add(j), keep.append((i, j))
    return sorted(keep), len(cand) - len(keep)


def test_correspondences_equal_the_sequential_greedy():
    rng = np.random.default_rng(7)
    for _ in range(1500):
        m, n = int(rng.integers(1, 12)), int(rng.integers(3, 25))
        vp = np.array([rng.choice(n, 3, replace=False) for _ in range(m)])
        vq = np.array([rng.choice(n, 3, replace=False) for _ in range(m)])
        scores = np.round(rng.normal(size=m), 1)  # ties in score happen
        pairs, n_conflicts = correspondences(vp, vq, scores)
        keep, dropped = _sequential_greedy(vp, vq, scores)
        assert [tuple(p) for p in pairs.tolist()] == keep
        assert n_conflicts == dropped


def test_big_maps_run_in_slices_with_the_same_results(monkeypatch):
    scenario = _scenario(40, 0.75, 30.0)
    matcher = {"method": "paper", "objective": "lr", "taus": ["oracle", "chi2:0.01"]}
    whole = run_chunk(0, scenario, matcher, 0, 12)
    monkeypatch.setattr(batched, "MAX_PAIRS", 4 * 75**2)  # 4 trials of 40 landmarks per slice
    sliced = run_chunk(0, scenario, matcher, 0, 12)
    for a, b in zip(whole, sliced):
        timeless = [c for c in a.columns if not c.startswith("time_")]
        pd.testing.assert_frame_equal(a[timeless], b[timeless], check_exact=True)
