"""One pipeline: the batch stages against their batch of one, and the harness against the library."""

import ast
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import mapmerge as mm
from experiments import trials as harness
from experiments.trials import run_chunk, trial_seeds

ROOT = Path(__file__).resolve().parent.parent


def _scenario(n, overlap, snr_db, unrelated=False, aspect=1.0):
    return {"kind": "synthetic", "n_landmarks": n, "overlap": overlap, "snr_db": snr_db,
            "aspect": aspect, "unrelated": unrelated}


def test_make_pairs_draws_what_make_pair_draws():
    seeds = trial_seeds(5, _scenario(12, 0.5, 20.0), range(7))
    batch = mm.simulate.make_pairs(12, 0.5, 20.0, seeds, aspect=1.5, unrelated=True)
    for k, seed in enumerate(seeds):
        one = mm.simulate.make_pair(12, 0.5, 20.0, rng=seed, aspect=1.5, unrelated=True)
        for name in ("p", "q", "ids_p", "ids_q", "truth", "sigma", "theta", "t", "sigma_bar2", "n_common"):
            np.testing.assert_array_equal(getattr(batch[k], name), getattr(one, name), err_msg=name)
    # A Generator is consumed as the seed it came from.
    gen = mm.simulate.make_pair(12, 0.5, 20.0, rng=np.random.default_rng(seeds[0]))
    np.testing.assert_array_equal(gen.p, mm.simulate.make_pair(12, 0.5, 20.0, rng=seeds[0]).p)


@pytest.mark.parametrize("method, n, snr_db, tau", [
    ("paper", 15, 25.0, "chi2:0.01"), ("cyclic", 20, 15.0, -4.0), ("consensus", 40, 30.0, "chi2:0.01"),
    ("groth", 25, 30.0, "chi2:0.01"),
])
def test_batch_equals_its_batches_of_one(method, n, snr_db, tau):
    batch = mm.simulate.make_pairs(n, 0.75, snr_db, list(range(6)))
    merged = mm.merge_batch(batch.p, batch.q, batch.sigma, tau=tau, method=method)
    for k in range(len(batch)):
        one = mm.merge_maps(batch.p[k], batch.q[k], batch.sigma[k], tau=tau, method=method)
        res = merged.result(k)
        assert res.matched == one.matched
        for name in ("pairs", "triangle_pairs", "triangle_log_lr", "declared", "merged", "index_p", "index_q",
                     "origin"):
            np.testing.assert_array_equal(getattr(res, name), getattr(one, name), err_msg=name)
        np.testing.assert_array_equal([res.theta, *res.t], [one.theta, *one.t])
        np.testing.assert_array_equal(res.tri_p.vertices, one.tri_p.vertices)
    assert merged.matched.any()


@pytest.mark.parametrize("scenario, method", [
    (_scenario(10, 0.75, 20.0), "paper"),
    (_scenario(20, 0.5, 0.0), "cyclic"),
    (_scenario(12, 0.75, 30.0, unrelated=True), "paper"),
    (_scenario(30, 0.75, 25.0), "consensus"),
])
def test_harness_rows_are_the_library_on_each_trial(scenario, method):
    """Same draws, same tentative pairs, same counts and errors as merge_maps on each trial alone."""
    taus = ["oracle", "chi2:0.01", "chi2:0.001"]
    rows, pairs = run_chunk(3, scenario, {"method": method, "objective": "lr", "taus": taus}, 20, 32)
    seeds = trial_seeds(3, scenario, range(20, 32))
    args = (scenario["n_landmarks"], scenario["overlap"], scenario["snr_db"])
    for k, seed in zip(range(20, 32), seeds):
        sc = mm.simulate.make_pair(*args, rng=seed, unrelated=scenario["unrelated"])
        for rule in taus[1:]:
            res = mm.merge_maps(sc.p, sc.q, sc.sigma, tau=rule, method=method)
            row = rows[(rows.trial == k) & (rows.tau == rule)].iloc[0]
            expected = mm.metrics.map_errors(sc, res)
            for key, value in expected.items():
                if isinstance(value, float) and np.isnan(value):
                    assert np.isnan(row[key]), key
                else:
                    assert row[key] == value, (k, rule, key)
            is_true, _ = mm.metrics.triangle_labels(sc.ids_p, sc.ids_q, res.tri_p.vertices, res.tri_q.vertices,
                                                    res.triangle_pairs)
            counts = mm.metrics.detection_counts(is_true, res.declared, len(mm.metrics.common_triangles(
                sc.ids_p, sc.ids_q, res.tri_p.vertices, res.tri_q.vertices)))
            assert {key: row[key] for key in counts} == counts
        if method != "consensus":  # the LP's tentative pairs and scores, bit for bit
            res = mm.merge_maps(sc.p, sc.q, sc.sigma, method=method)
            np.testing.assert_array_equal(pairs[pairs.trial == k].score.to_numpy(), res.triangle_log_lr)
    # The cells exercise what they should: merges, detections only on related
    # maps, and conflicting correspondences at 0 dB.
    assert rows.matched.any()
    if scenario["unrelated"]:
        assert (rows.tp == 0).all()
    elif scenario["snr_db"] >= 10:
        assert (rows.tp > 0).any()
    else:
        assert (rows.n_conflicts > 0).any()


def test_harness_on_realistic_maps_is_the_library_with_covariances_and_the_oracle():
    """Interleaved layout, clutter and anisotropic noise: the harness passes the
    scenario's covariances, and its oracle columns are the oracle association's."""
    extra = {"layout": "interleaved", "p_detect": 0.8, "clutter": 0.1, "anisotropy": 2.0}
    scenario = {**_scenario(40, 0.75, 25.0), **extra}
    matcher = {"method": "consensus", "objective": "lr", "taus": ["chi2:0.01"], "use_cov": True, "oracle": True}
    rows, _ = run_chunk(4, scenario, matcher, 0, 6)
    for k, seed in enumerate(trial_seeds(4, scenario, range(6))):
        sc = mm.simulate.make_pair(40, 0.75, 25.0, rng=seed, **extra)
        assert sc.p.shape == (44, 2)
        res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus", cov_p=sc.cov_p, cov_q=sc.cov_q)
        row = rows[rows.trial == k].iloc[0]
        for key, value in mm.metrics.map_errors(sc, res).items():
            assert row[key] == value or (np.isnan(value) and np.isnan(row[key])), (k, key)
        oracle = mm.metrics.oracle_association(sc.p, sc.q, sc.theta, sc.t, sc.cov_p, sc.cov_q, sc.density,
                                               sc.p_shared)
        right = np.sum(sc.ids_p[oracle[:, 0]] == sc.ids_q[oracle[:, 1]])
        assert (row.oracle_correct_pairs, row.oracle_wrong_pairs) == (right, len(oracle) - right)
    assert rows.transform_found.all() and (rows.tp_implied <= rows.tp).all()
    # The cell differs from the strip layout's: its seeds depend on the new keys.
    assert harness.cell_key(scenario) != harness.cell_key(_scenario(40, 0.75, 25.0))
    assert harness.cell_key({**_scenario(40, 0.75, 25.0), "layout": "strip", "p_detect": 0.9, "clutter": 0.0,
                             "anisotropy": 0.0}) == harness.cell_key(_scenario(40, 0.75, 25.0))


def test_example_merged_map_uses_the_covariances_when_the_matcher_does():
    """The example tables (the figures' and the Victoria Park table's fused rows) merge as the trials do."""
    from experiments.examples import example_tables

    extra = {"layout": "interleaved", "p_detect": 0.8, "clutter": 0.0, "anisotropy": 2.0}
    scenario = {**_scenario(40, 0.75, 25.0), **extra}
    matcher = {"method": "consensus", "objective": "lr", "taus": ["chi2:0.01"], "use_cov": True}
    merged = example_tables(4, scenario, matcher, [0])["example_landmarks"].query("kind == 'merged'")
    sc = mm.simulate.make_pair(40, 0.75, 25.0, rng=trial_seeds(4, scenario, [0])[0], **extra)
    with_cov = mm.merge_maps(sc.p, sc.q, sc.sigma, cov_p=sc.cov_p, cov_q=sc.cov_q).combined.points
    without = mm.merge_maps(sc.p, sc.q, sc.sigma).combined.points
    assert np.array_equal(merged[["x", "y"]].to_numpy(), with_cov)
    assert not np.array_equal(with_cov, without)  # information weighting moves the fused rows


def test_chunking_does_not_change_results():
    scenario = _scenario(15, 0.75, 10.0)
    matcher = {"method": "cyclic", "objective": "lr", "taus": ["oracle", "chi2:0.01"]}
    whole = run_chunk(0, scenario, matcher, 0, 90)
    parts = [run_chunk(0, scenario, matcher, a, b) for a, b in ((0, 1), (1, 37), (37, 90))]
    for k in (0, 1):
        joined = pd.concat([p[k] for p in parts], ignore_index=True)
        timeless = [c for c in whole[k].columns if not c.startswith("time_")]
        pd.testing.assert_frame_equal(whole[k][timeless], joined[timeless], check_exact=True)


def test_big_maps_run_in_slices_with_the_same_results(monkeypatch):
    scenario = _scenario(40, 0.75, 30.0)
    matcher = {"method": "paper", "objective": "lr", "taus": ["oracle", "chi2:0.01"]}
    whole = run_chunk(0, scenario, matcher, 0, 12)
    monkeypatch.setattr(harness, "MAX_PAIRS", 4 * 75**2)  # 4 trials of 40 landmarks per slice
    sliced = run_chunk(0, scenario, matcher, 0, 12)
    for a, b in zip(whole, sliced):
        timeless = [c for c in a.columns if not c.startswith("time_")]
        pd.testing.assert_frame_equal(a[timeless], b[timeless], check_exact=True)


def _imports(package: str):
    """(module, imported module, imported names) for every import inside ``package``."""
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        pkg = parts[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(pkg[: len(pkg) - node.level + 1] + ([base] if base else []))
                yield module, base, [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    yield module, alias.name, []


def test_no_import_cycles():
    modules = {m for pkg in ("mapmerge", "experiments") for m, _, _ in _imports(pkg)}
    edges = {m: set() for m in modules}
    for pkg in ("mapmerge", "experiments"):
        for module, base, names in _imports(pkg):
            for target in [base, *(f"{base}.{n}" for n in names)]:
                if target in modules and target != module and not module.startswith(target + "."):
                    edges[module].add(target)
    state = {}

    def visit(u, stack):
        state[u] = 1
        for v in sorted(edges[u]):
            assert state.get(v) != 1, "import cycle: " + " -> ".join(stack[stack.index(v):] + [v])
            if v not in state:
                visit(v, stack + [v])
        state[u] = 2

    for m in sorted(modules):
        if m not in state:
            visit(m, [m])


def test_experiments_import_no_private_names_of_the_library():
    private = [(m, base, n) for m, base, names in _imports("experiments") if base.startswith("mapmerge")
               for n in names if n.startswith("_")]
    private += [(m, base, "") for m, base, _ in _imports("experiments")
                if base.startswith("mapmerge") and any(part.startswith("_") for part in base.split(".")[1:])]
    assert private == []


def test_the_library_never_imports_hydra():
    assert not [m for m, base, _ in _imports("mapmerge") if base.split(".")[0] in ("hydra", "omegaconf")]
