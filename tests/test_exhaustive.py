"""The exhaustive ML detector (a limit for the matchers, not a method)."""

import re

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import ConvexHull

import mapmerge as mm
from mapmerge import exhaustive


def test_detector_finds_the_transform_and_separates_related_from_unrelated():
    related = mm.simulate.make_pair(60, 0.75, 10, rng=10001)
    unrelated = mm.simulate.make_pair(60, 0.75, 10, rng=10001, unrelated=True)
    value, theta, t = exhaustive.max_log_lr(related.p, related.q, related.sigma, 0.9, related.density)
    assert mm.metrics.transform_found(related, theta, t)
    # The maximum is at least Λ at the true transform (the grid and EM find the peak).
    s = np.sqrt(2) * related.sigma
    c = exhaustive.bump_height(related.density, 1.0, s, 0.9)
    at_truth, _ = exhaustive.Mixture.of_map(related.p, s, c, 0.9).log_lr(related.q, related.theta, related.t)
    assert value >= at_truth - 1e-9
    null, _, _ = exhaustive.max_log_lr(unrelated.p, unrelated.q, unrelated.sigma, 0.9, unrelated.density)
    assert value > null + 10


@pytest.mark.parametrize("kwargs, match", [
    ({"sigma": 0.0}, "sigma must be a positive finite number"),
    ({"p_shared": 1.0}, r"p_shared must lie in \(0, 1\) and density be > 0, got 1.0"),
    ({"density": -1.0}, r"p_shared must lie in \(0, 1\) and density be > 0"),
    ({"P": np.ones((5, 2))}, "P contains duplicate points"),
    ({"Q": np.full((5, 2), np.nan)}, "Q contains NaN or inf"),
    ({"Q": np.ones(5)}, r"Q must have shape \(n, 2\)"),
])
def test_detector_rejects_bad_arguments(kwargs, match):
    sc = mm.simulate.make_pair(20, 0.75, 10, rng=1)
    args = {"P": sc.p, "Q": sc.q, "sigma": sc.sigma, "p_shared": 0.9, "density": 1.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        exhaustive.max_log_lr(**args)


@pytest.mark.parametrize("snr", [10.0, 25.0])
def test_null_log_tail_bounds_the_tail_of_unrelated_maps_and_is_not_vacuous(snr):
    # Λ at a fixed transform of 60 q landmarks uniform over p's hull, 2,000 draws.
    sc = mm.simulate.make_pair(100, 0.75, snr, rng=7)
    hull = ConvexHull(sc.p)
    s = np.sqrt(2) * sc.sigma
    model = exhaustive.Mixture.of_map(sc.p, s, exhaustive.bump_height(sc.density, 1.0, s, 0.5), 0.5)
    rng = np.random.default_rng(1)
    lo, hi = sc.p.min(axis=0), sc.p.max(axis=0)
    values = []
    for _ in range(2000):
        x = rng.uniform(lo, hi, (400, 2))
        x = x[mm.exhaustive.inside_hull(hull, x)][:60]
        values.append(model.log_lr(x, 0.0, np.zeros(2))[0])
    for q in (0.9, 0.99):
        level = np.quantile(values, q)
        bound = model.null_log_tail([level], [60])[0]
        # An upper bound on the tail probability, and within a factor e^3 of it.
        assert np.log(1 - q) - 0.1 <= bound <= np.log(1 - q) + 3.0


def test_null_log_tail_on_a_subsample_of_landmark_discs_matches_every_disc(monkeypatch):
    # 1,200 landmarks: the quadrature uses every third disc, scaled up; every disc gives the reference.
    sc = mm.simulate.make_pair(1200, 0.75, 15.0, rng=2)
    s = np.sqrt(2) * sc.sigma
    model = exhaustive.Mixture.of_map(sc.p, s, exhaustive.bump_height(sc.density, 1.0, s, 0.5), 0.5)
    levels, inside = [100.0, 400.0, 900.0], [900, 900, 900]
    sub = model.null_log_tail(levels, inside)
    monkeypatch.setattr(exhaustive, "QUAD_MAX_CENTRES", 10_000)
    full = model.null_log_tail(levels, inside)
    assert np.all(full < -10) and np.allclose(sub, full, rtol=0.05)


def test_mixtures_give_each_model_s_em_and_log_lr_bit_for_bit():
    sc = mm.simulate.make_pairs(40, 0.75, 12.0, [1, 2, 3])
    s = np.sqrt(2.0) * sc.sigma
    models = [exhaustive.Mixture.of_map(p, float(r), exhaustive.bump_height(40, ConvexHull(p).volume, float(r), 0.5),
                                        0.5) for p, r in zip(sc.p, s)]
    model = np.array([0, 2, 1, 1, 0, 2])
    rng = np.random.default_rng(0)
    theta = sc.theta[model] + rng.normal(0, 0.02, 6)
    t = sc.t[model] + rng.normal(0, 0.3, (6, 2))
    t[4] += 50.0  # far off: EM stops at once
    mixtures = exhaustive.Mixtures.of(models)
    em_theta, em_t = mixtures.em(sc.q, model, theta, t)
    log_lr, n_inside = mixtures.log_lr(sc.q, model, em_theta, em_t)
    for k, m in enumerate(model):
        alone = models[m].em(sc.q[m], theta[k], t[k])
        assert em_theta[k] == alone[0] and np.array_equal(em_t[k], alone[1])
        assert (log_lr[k], n_inside[k]) == models[m].log_lr(sc.q[m], em_theta[k], em_t[k])
    assert n_inside[4] == 0 and np.all(n_inside[[0, 1, 2, 3, 5]] > 10)


def test_limit_experiment_resumes_without_recomputing_finished_pairs(tmp_path, monkeypatch):
    from experiments import detector

    calls = []

    def fake_statistic(n, layout, snr, seed, unrelated):
        calls.append("detector")
        return float(seed % 97) + snr, not unrelated, 0.0

    def fake_consensus(n, layout, snr, seed, unrelated):
        calls.append("consensus")
        # Then the stages' statistics, which the limit table does not read.
        return (seed % 2 == 0, seed % 3 == 0 and not unrelated, seed % 5, seed % 2,
                np.inf, 0, 0, False, np.inf, 1.0, np.inf, False)

    def fake_oracle(n, layout, snr, seed, unrelated):
        calls.append("oracle")
        return seed % 7, 1, seed % 7 + 1, 2

    def fake_correspondence(n, layout, snr, seed, unrelated):
        calls.append("correspondence")
        return (not unrelated and seed % 4 != 1,)

    grid_measures = [columns for measure, columns in detector.MEASURES if measure is not detector.pair_statistic]
    monkeypatch.setattr(detector, "MEASURES", tuple(zip((fake_statistic, fake_consensus, fake_oracle,
                                                         fake_correspondence), grid_measures)))
    path, snrs = tmp_path / "pairs.csv", (0.0, 2.5)
    fresh = detector.run_pairs(8, 1, path, snrs)
    n = 2 * 2 * 2 * 8  # layouts x SNRs x (null, related) x trials
    assert len(fresh) == n and calls.count("detector") == calls.count("consensus") == n
    # Interrupted after some pairs, or a measure added later: only what is
    # missing is computed again, and the table is the uninterrupted run's.
    partial = fresh.iloc[:20].copy()
    partial.loc[:9, "consensus_wrong"] = np.nan
    partial.to_csv(path, index=False)
    calls.clear()
    resumed = detector.run_pairs(8, 1, path, snrs)
    assert calls.count("detector") == n - 20 and calls.count("consensus") == n - 10
    pd.testing.assert_frame_equal(resumed, fresh)
    # A shorter run reads its pairs from the file and keeps the others in it.
    calls.clear()
    short = detector.run_pairs(4, 1, path, snrs)
    assert not calls and len(short) == n // 2 and len(pd.read_csv(path)) == n
    # A file from before other map sizes were measured holds 100-landmark pairs; another size adds its own.
    pd.read_csv(path).drop(columns="n_landmarks").to_csv(path, index=False)
    pd.testing.assert_frame_equal(detector.run_pairs(8, 1, path, snrs), fresh)
    both = detector.run_pairs(8, 1, path, snrs, landmarks=(100, 10))
    assert calls.count("detector") == n and len(both) == 2 * n and len(pd.read_csv(path)) == 2 * n
    assert list(detector.limit_table(both).n_landmarks) == [100] * 4 + [10] * 4
    table = detector.limit_table(fresh)
    assert list(table.consensus_false_merges) == [4] * 4  # even seeds among 8 unrelated per cell
    # Association is judged where consensus found the transform: seeds divisible by 3.
    related = fresh[~fresh.unrelated & (fresh.seed % 3 == 0)]
    assert table.consensus_correct_vs_oracle.iloc[0] == pytest.approx(
        (related.seed % 5).iloc[:2].sum() / (related.seed % 7).iloc[:2].sum())
    assert table.consensus_wrong_vs_transform_oracle.iloc[0] == pytest.approx((related.seed % 2).iloc[:2].sum() / 4)
    # fake_statistic finds every related transform: accurate whatever the threshold, found only above it.
    assert list(table.ml_accurate_rate) == [1.0] * 4
    assert (table.found_rate == table.detected_rate).all() and (table.found_rate <= table.ml_accurate_rate).all()
    # The correspondence oracle misses the related seeds 4k + 1: 2 of the 8 per cell.
    assert list(table.correspondence_found_rate) == [0.75] * 4


@pytest.mark.parametrize("argv, message", [
    (["--landmarks", "2"], "--landmarks 2: must be an integer >= 3"),
    # 0.75 x 3 rounds to 2 common landmarks: the landmark count is at fault, not the fixed overlap.
    (["--landmarks", "3"], "--landmarks 3: must make overlap * n_landmarks round to at least 3"),
    (["--snrs", "1000"], "--snrs 1000.0: must be a number of dB"),
])
def test_detector_refuses_bad_arguments_in_one_line_naming_them(tmp_path, argv, message):
    from experiments import detector

    with pytest.raises(SystemExit, match=re.escape(message)):
        detector.main([*argv, "--trials", "8", "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("scale, sigma", [(1.0, 1e-9), (1e3, None)])
def test_detector_refuses_a_grid_beyond_its_budget(scale, sigma):
    """The grid is set by the maps' extents in units of σ: a tiny σ or maps in different units would ask
    for any size; beyond ``MAX_GRID_SIDE`` cells per axis the detector refuses in one line."""
    sc = mm.simulate.make_pair(20, 0.75, 10, rng=1)
    with pytest.raises(ValueError, match=r"grid cells .* per axis .* sigma and both maps in the same units"):
        exhaustive.max_log_lr(sc.p, sc.q * scale, sigma or sc.sigma, 0.9, 1.0)


@pytest.mark.parametrize("n, snr, unrelated", [(10, 20.0, False), (60, 15.0, True)])
def test_grid_cells_are_the_argmax_of_the_convolved_votes_and_hull_counts(n, snr, unrelated):
    """The grid's best cell per rotation against the textbook form: the pair votes convolved with the
    bump, plus log(1 - π) times the q landmarks inside p's hull (a correlation of two rasters), by FFT."""
    from scipy.signal import fftconvolve

    from mapmerge.alignment import rotate

    sc = mm.simulate.make_pair(n, 0.75, snr, rng=1, unrelated=unrelated)
    s = np.sqrt(2) * sc.sigma
    c, p_shared = exhaustive.bump_height(sc.density, 1.0, s, 0.9), 0.9
    pc, qc = sc.p - sc.p.mean(0), sc.q - sc.q.mean(0)
    h, K = exhaustive.GRID_STEP * s, int(np.ceil(exhaustive.KERNEL_SIGMAS / exhaustive.GRID_STEP))
    off = h * np.arange(-K, K + 1)
    kernel = np.log1p(c * np.exp(-(off[:, None] ** 2 + off[None, :] ** 2) / (2 * s**2)))
    Ka = int(np.ceil(np.sqrt(np.max(np.sum(qc**2, 1))) / h))
    Kb = int(np.ceil(np.sqrt(np.max(np.sum(pc**2, 1))) / h))
    M, hull = Ka + Kb, ConvexHull(pc)
    side = 2 * M + 1
    u = np.rint(qc / h).astype(np.int64) + Ka
    thetas = np.linspace(0, 2 * np.pi, 12, endpoint=False) + 0.1
    cells = exhaustive._grid_best_cells(pc, qc, thetas, h, M, kernel, np.log(1 - p_shared), hull.equations, u, Kb)
    A = np.zeros((2 * Ka + 1, 2 * Ka + 1))
    np.add.at(A, tuple(u.T), 1.0)
    grid_b = h * np.stack(np.meshgrid(np.arange(-Kb, Kb + 1), np.arange(-Kb, Kb + 1), indexing="ij"), -1)
    for theta, cell in zip(thetas, cells):
        votes = np.rint((qc[None] - rotate(theta, pc)[:, None]).reshape(-1, 2) / h).astype(np.int64) + M
        counts = np.bincount(votes[:, 0] * side + votes[:, 1], minlength=side * side).reshape(side, side)
        B = exhaustive.inside_hull(hull, rotate(-theta, grid_b).reshape(-1, 2)).reshape(grid_b.shape[:2])
        value = (fftconvolve(counts, kernel, mode="same")
                 + np.log(1 - p_shared) * np.rint(fftconvolve(A, B[::-1, ::-1].astype(float), mode="full")))
        assert value[tuple(cell)] == pytest.approx(value.max(), rel=1e-9, abs=1e-9)


def test_pair_maximiser_finds_the_transform_and_the_chance_maxima_the_grid_misses():
    from experiments import detector

    for seed in (4, 7):
        sc = mm.simulate.make_pair(10, 0.75, 20, rng=seed)
        value, theta, t = detector.pair_max_log_lr(sc.p, sc.q, sc.sigma, 0.75, sc.density)
        s = np.sqrt(2) * sc.sigma
        model = exhaustive.Mixture.of_map(sc.p, s, exhaustive.bump_height(sc.density, 1.0, s, 0.75), 0.75)
        assert mm.metrics.transform_found(sc, theta, t) and value >= model.log_lr(sc.q, sc.theta, sc.t)[0] - 1e-9
    # Unrelated pairs whose best chance alignment falls between the grid's cells.
    for seed in (1, 4, 5):
        sc = mm.simulate.make_pair(10, 0.75, 20, rng=seed, unrelated=True)
        grid = exhaustive.max_log_lr(sc.p, sc.q, sc.sigma, 0.75, sc.density)[0]
        assert detector.pair_max_log_lr(sc.p, sc.q, sc.sigma, 0.75, sc.density)[0] > grid + 0.5
    with pytest.raises(ValueError, match="P and Q must be"):
        detector.pair_max_log_lr(np.ones(4), sc.q, sc.sigma, 0.75, sc.density)


def test_null_threshold_is_the_empirical_quantile_given_enough_null_pairs():
    from experiments import detector

    null = np.random.default_rng(0).gumbel(size=10_000)
    threshold, rule = detector.null_threshold(null, 1e-3)
    assert rule == "empirical" and np.sum(null > threshold) <= 10 < np.sum(null >= threshold) + 1
    # Fewer pairs: the exponential tail's extrapolation, near the Gumbel law's 1e-3 quantile (6.9).
    threshold, rule = detector.null_threshold(null[:1000], 1e-3)
    assert rule == "tail" and abs(threshold - 6.9) < 1.0


def test_stage_table_keeps_every_rule_within_the_false_alarm_budget():
    from experiments import detector

    rng = np.random.default_rng(3)
    n_null, n_related = 4000, 200

    def pairs(n, unrelated, shift):
        group = rng.random(n) < 0.4
        return pd.DataFrame({"n_landmarks": 10, "layout": "strip", "snr_db": 20.0, "unrelated": unrelated,
                             "consensus_found": False, "consensus_merged": False,
                             "tri_log_nfa": np.where(group, rng.normal(2 - shift, 2, n), np.inf),
                             "tri_hypotheses": np.where(group, 5, 0), "tri_found": group & (shift > 0),
                             "search_log_nfa": rng.normal(6 - shift, 2, n), "search_log_hypotheses": 15.0,
                             "search_log_tail": rng.normal(-9 - shift, 2, n), "search_found": shift > 0})

    runs = pd.concat([pairs(n_null, True, 0.0), pairs(n_related, False, 8.0)], ignore_index=True)
    row = detector.stage_table(runs, 1e-3).iloc[0]
    assert row.null_pairs == n_null and row.related_pairs == n_related
    for stat in detector.STAGE_STATISTICS:
        assert row[f"{stat}_null_pass"] <= 4
    assert row.combined_null_pass <= 4 and 0.5 < row.combined_found_rate <= 1
    assert row.related_tri_group_rate == pytest.approx(np.isfinite(runs.tri_log_nfa[~runs.unrelated]).mean())
