"""Aggregation into ROC curves and tables, figures from tables, docs from results."""

import os
import shutil

import numpy as np
import pandas as pd
import pytest

from experiments.aggregate import aggregate
from experiments.docs import refresh
from experiments.examples import _triangle_status
from experiments.figures import draw_aggregate, draw_all
from harness_utils import cli


def test_multirun_end_to_end_through_aggregation_and_figures(tmp_path):
    results = tmp_path / "results"
    # One job after another in this process: the joblib launcher has its own test (test_run.py).
    fig3 = cli(["-m", "experiment=fig3", "hydra/launcher=basic", "mc.n_trials=12", "mc.chunk_size=6",
                "scenario.snr_db=15,40", f"aggregate_dir={results / 'fig3'}",
                "mc.progress=false"], tmp_path, timeout=300)
    assert fig3.returncode == 0, fig3.stderr[-2000:]
    smoke = cli(["-m", "experiment=smoke", f"aggregate_dir={results / 'fig1'}"], tmp_path)
    assert smoke.returncode == 0, smoke.stderr[-2000:]
    (results / "fig2").mkdir()
    os.link(results / "fig1" / "examples_landmarks.csv", results / "fig2" / "examples_landmarks.csv")

    auc = pd.read_csv(results / "fig3" / "auc.csv")
    assert len(auc) == 8 and auc.n_trials.eq(12).all()
    assert (auc[auc.snr_db == 40].auc.to_numpy() > auc[auc.snr_db == 15].auc.to_numpy()).all()
    table = pd.read_csv(results / "fig3" / "table.csv")
    assert set(table.tau) == {"oracle", "chi2:0.01", "chi2:0.001"} and len(table) == 24
    roc = pd.read_csv(results / "fig3" / "roc.csv")
    assert roc.groupby(["n_landmarks", "overlap", "snr_db"]).p_fa.is_monotonic_increasing.all()
    md = (results / "fig1" / "table.md").read_text()
    assert md.startswith("|") and "p_d" in md and "p_fa" in md
    examples = pd.read_csv(results / "fig1" / "examples_landmarks.csv")
    assert set(examples["kind"]) == {"p", "q", "merged", "truth"}

    made = draw_all(results)
    assert {p.name for p in made} == {f"fig{i}.{e}" for i in (1, 2, 3) for e in ("png", "pdf")}
    assert all(p.stat().st_size > 10_000 for p in made)
    made = draw_aggregate(results / "fig3")
    assert {p.name for p in made} == {"roc.png", "roc.pdf"}


def test_tau_rules_split_across_jobs_count_each_trial_once(tmp_path):
    common = ["scenario=small", "mc.n_trials=60", "mc.progress=false"]
    split = cli(["-m", "matcher.taus=[chi2:0.01],[chi2:0.05],[-3]", *common, f"hydra.sweep.dir={tmp_path / 's'}"],
                tmp_path)
    one = cli(["matcher.taus=[chi2:0.01,chi2:0.05,-3]", *common, f"hydra.run.dir={tmp_path / 'one'}"], tmp_path)
    assert split.returncode == 0 and one.returncode == 0, split.stderr[-2000:] + one.stderr[-2000:]
    aggregate([tmp_path / "one"], tmp_path / "one_agg")
    for name in ("auc.csv", "roc.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "s" / "aggregate" / name),
                                      pd.read_csv(tmp_path / "one_agg" / name))
    a = pd.read_csv(tmp_path / "s" / "aggregate" / "table.csv").sort_values("tau", ignore_index=True)
    b = pd.read_csv(tmp_path / "one_agg" / "table.csv").sort_values("tau", ignore_index=True)
    pd.testing.assert_frame_equal(a, b)
    assert pd.read_csv(tmp_path / "one_agg" / "auc.csv").n_trials.item() == 60
    # A second sweep into the same directory adds its cells (one of them already there, with fewer
    # trials: counted once): the directory's aggregate keeps every cell of both.
    more = cli(["-m", "scenario=small", "scenario.snr_db=20,40", "matcher.taus=[chi2:0.01]", "mc.n_trials=8",
                "mc.n_jobs=1", f"hydra.sweep.dir={tmp_path / 's'}"], tmp_path, CI="")
    assert more.returncode == 0, more.stderr[-2000:]
    table = pd.read_csv(tmp_path / "s" / "aggregate" / "table.csv")
    assert table.groupby(["snr_db", "tau"]).n_trials.max().to_dict() == {
        (20, "-3"): 60, (20, "chi2:0.01"): 60, (20, "chi2:0.05"): 60, (40, "chi2:0.01"): 8}
    from experiments.aggregate import main

    main([str(tmp_path / "s"), "--out", str(tmp_path / "again")])
    for name in ("table.csv", "auc.csv", "roc.csv"):
        assert (tmp_path / "again" / name).read_bytes() == (tmp_path / "s" / "aggregate" / name).read_bytes()
    # The sweep's overall progress bar (trials still to run: 8 of 16 were cached; cells done).
    assert "sweep: 100%" in more.stderr and "8/8 [" in more.stderr and "cells 2/2" in more.stderr
    # A run written before the scenario's later columns existed reads at their first-release values.
    shutil.copytree(tmp_path / "one", tmp_path / "older")
    for path in (tmp_path / "older").glob("summary_*.parquet"):  # so old a run has no summaries either
        path.unlink()
    trials = pd.read_parquet(tmp_path / "older" / "trials.parquet")
    assert (trials.layout == "strip").all() and (trials.p_detect == 0.9).all()
    trials.drop(columns=["layout", "p_detect"]).to_parquet(tmp_path / "older" / "trials.parquet")
    aggregate([tmp_path / "older"], tmp_path / "older_agg")
    for name in ("table.csv", "auc.csv", "roc.csv"):
        assert (tmp_path / "older_agg" / name).read_bytes() == (tmp_path / "one_agg" / name).read_bytes(), name
    # Timings that do not belong to the trials row for row are refused.
    pd.read_parquet(tmp_path / "older" / "timings.parquet").iloc[::-1].to_parquet(
        tmp_path / "older" / "timings.parquet")
    with pytest.raises(ValueError, match="row for row"):
        aggregate([tmp_path / "older"], tmp_path / "older_agg2")
    # The same trials in two runs of one cell count once (their union) ...
    shutil.copytree(tmp_path / "one", tmp_path / "copy")
    aggregate([tmp_path / "one", tmp_path / "copy"], tmp_path / "twice")
    for name in ("table.csv", "auc.csv", "roc.csv"):
        assert (tmp_path / "twice" / name).read_bytes() == (tmp_path / "one_agg" / name).read_bytes(), name
    # ... unless they differ: the trials are named and nothing is written.
    trials = pd.read_parquet(tmp_path / "copy" / "trials.parquet")
    trials.loc[(trials.trial == 7) & (trials.tau == "-3"), "tp"] += 1
    trials.to_parquet(tmp_path / "copy" / "trials.parquet")
    with pytest.raises(ValueError, match=r"1 trial\(s\) of cell .* differ between runs .*: trial 7 \(seed 0, "
                       r"τ rule -3\) in .*copy and .*one; aggregate those runs apart"):
        aggregate([tmp_path / "one", tmp_path / "copy"], tmp_path / "conflict")
    assert not (tmp_path / "conflict").exists()


def test_example_triangle_status_prefers_the_telling_pair():
    pairs = np.array([[0, 5], [0, 6], [1, 7], [2, 8]])
    is_true = np.array([True, False, False, True])
    declared = np.array([True, False, False, False])
    common = np.array([[0, 5], [1, 9], [2, 8]])
    status = _triangle_status(4, 0, pairs, is_true, declared, common)
    assert list(status) == ["tp", "unpaired", "md", "other"]


def test_docs_includes_are_refreshed_from_results(tmp_path):
    (tmp_path / "results").mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "results" / "t.md").write_text("# Title\n\n## Part\n\n| a |\n|---|\n| 1 |\n![f](f.png)\n")
    page = tmp_path / "docs" / "results.md"
    page.write_text("intro\n<!-- include: results/t.md -->\nold numbers\n<!-- end include -->\nrest\n")
    assert refresh(page, tmp_path) == ["results/t.md"]
    text = page.read_text()
    assert "old numbers" not in text and "# Title" not in text
    assert "#### Part" in text and "| 1 |" in text and "![f](../results/f.png)" in text
    assert text.startswith("intro\n") and text.endswith("<!-- end include -->\nrest\n")


def test_compare_sweep_tables_and_figure_on_both_layouts(tmp_path):
    """A small version of the compare experiment: both layouts, the oracle curve, the figure."""
    from experiments.compare import write_tables

    out = tmp_path / "compare"
    run = cli(["-m", "experiment=compare", "mc.n_trials=6", "mc.chunk_size=3", "scenario.n_landmarks=40",
               "matcher.method=consensus", "scenario.snr_db=30", f"aggregate_dir={out / 'compare'}",
               "mc.progress=false"], tmp_path, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    # The exhaustive detector's limit curve is drawn when its table exists.
    (tmp_path / "detector").mkdir()
    pd.DataFrame({"layout": ["strip", "interleaved"], "snr_db": [30.0, 30.0], "found_rate": [1.0, 1.0]}).to_csv(
        tmp_path / "detector" / "limit.csv", index=False)
    # A sweep for the association alone (many pairs at low SNR) is tabulated apart, not mixed in,
    # with the intervals of its ratios from its found pairs.
    from experiments.aggregate import find_runs
    from experiments.compare import found_pairs

    (out / "compare_association").mkdir()
    table = pd.read_csv(out / "compare" / "table.csv")
    table = table[~table.unrelated.astype(bool)]
    table.to_csv(out / "compare_association" / "table.csv", index=False)
    pairs = found_pairs(find_runs([tmp_path / "outputs" / "sweeps" / "compare"]))
    pairs = pairs.merge(table[["layout", "snr_db"]].drop_duplicates())  # the related cells
    assert len(pairs) == 12 and set(pairs.layout) == {"strip", "interleaved"}  # 6 related pairs per layout
    pairs.to_csv(out / "compare_association" / "found_pairs.csv", index=False)
    made = write_tables(out)
    assert {p.name for p in made} >= {"compare.csv", "summary.md", "success.png", "association.csv"}
    comp = pd.read_csv(out / "compare.csv")
    assert not comp.duplicated(["layout", "snr_db", "method", "tau"]).any()
    assert set(comp.layout) == {"strip", "interleaved"} and set(comp.method) == {"consensus"}
    assert comp.n_trials_unrelated.eq(6).all() and comp.oracle_correct_per_trial.notna().all()
    consensus = comp[(comp.method == "consensus") & (comp.snr_db == 30)]
    assert (consensus.found_rate == 1).all() and (consensus.false_merges == 0).all()
    # At 30 dB consensus pairs as the oracle association does, within a pair per trial (the
    # oracle maximises the posterior, so a matcher may now and then pair one more correctly).
    assert np.allclose(consensus.correct_per_trial, consensus.oracle_correct_per_trial, atol=1.0)
    assert "interleaved" in (out / "summary.md").read_text()
    # The low-SNR tables: transform found with its interval, and the 90 % crossing against the detector.
    found = pd.read_csv(out / "found.csv")
    assert set(found.layout) == {"strip", "interleaved"} and (found["95 % low"] <= found["transform found"]).all()
    assert found["false merges"].eq(0).all() and found["false-merge rate, 95 % high"].between(0.3, 0.5).all()
    # Every transform found at 30 dB: the association on found pairs is the association on all pairs.
    both = found.merge(consensus[consensus.tau != "oracle"], left_on=["layout", "SNR"], right_on=["layout", "snr_db"])
    assert len(both) == 2
    assert np.allclose(both["correct vs oracle (found)"], both.correct_per_trial / both.oracle_correct_per_trial)
    assert np.allclose(both["wrong vs oracle (found)"], both.wrong_per_trial / both.oracle_wrong_per_trial,
                       equal_nan=True)
    # The transform oracle (true transform, π estimated) pairs as consensus does once the transform is found.
    assert both["correct vs transform oracle (found)"].between(0.97, 1.03).all()
    association = pd.read_csv(out / "association.csv")
    assert list(association.layout) == ["strip", "interleaved"] and association["transform found (pairs)"].eq(6).all()
    cols = ["correct vs oracle (found)", "wrong vs oracle (found)"]
    assert np.allclose(association[cols], found.set_index("layout").loc[association.layout, cols], equal_nan=True)
    for col, interval in zip(cols, ("correct: 95 % interval", "wrong: 95 % interval")):
        bounds = association[interval].dropna().str.split("-", expand=True).astype(float)
        ratio = association.loc[bounds.index, col]
        assert ((bounds[0] <= ratio + 5e-4) & (ratio <= bounds[1] + 5e-4)).all()
    crossing = pd.read_csv(out / "crossing.csv").set_index(["layout", "method"])
    assert crossing.loc[("strip", "consensus"), "behind the detector (dB)"] == 0
    # Rebuilt where git has no timing.csv (a clone): the times last written are kept.
    written = {p.name: p.read_bytes() for p in made if p.suffix in (".csv", ".md")}
    for timing in out.glob("*/timing.csv"):
        timing.unlink()
    assert {p.name: p.read_bytes() for p in write_tables(out) if p.suffix in (".csv", ".md")} == written
    # A peer's sweep (here consensus's trials under a peer's name): no triangle counts, its own figure.
    peer = pd.read_csv(out / "compare" / "table.csv")
    peer = peer[peer.tau == "chi2:0.01"].assign(method="clipper", tau="none")
    (out / "compare_clipper").mkdir()
    peer.to_csv(out / "compare_clipper" / "table.csv", index=False)
    made = {p.name for p in write_tables(out)}
    assert {"peers.png", "success.png"} <= made
    comp = pd.read_csv(out / "compare.csv")
    clipper = comp[comp.method == "clipper"]
    assert len(clipper) == 2 and clipper.recall_common.isna().all() and clipper.found_rate.eq(1).all()
    assert "clipper" in set(pd.read_csv(out / "found.csv").method)


def test_realistic_sweep_summary_against_the_oracle(tmp_path):
    """A small version of the realistic experiment: interleaved, clutter, anisotropic noise."""
    from experiments.realistic import summary

    out = tmp_path / "realistic"
    run = cli(["-m", "experiment=realistic", "mc.n_trials=4", "scenario.n_landmarks=40", "scenario.snr_db=30",
               "scenario.clutter=0.1", "scenario.anisotropy=2.0", f"aggregate_dir={out}", "mc.progress=false"],
              tmp_path, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    s = summary(pd.read_csv(out / "table.csv"))
    assert len(s) == 1 and s["unrelated pairs"].iloc[0] == 4 and s["false merges"].iloc[0] == 0
    assert s["transform found"].iloc[0] == 1 and abs(s["correct vs oracle"].iloc[0] - 1) < 0.05


def test_ratio_interval_is_the_delta_method_interval_of_a_ratio_of_sums():
    from experiments.compare import ratio_interval

    # Every unit at the same ratio: no spread, a zero-width interval at it.
    assert np.allclose(ratio_interval([2, 4, 6], [1, 2, 3]), (2.0, 2.0))
    # x = (1, 3), y = (1, 1): R = 2, residuals (-1, 1), SE = √(2 / 2) / 1 = 1.
    low, high = ratio_interval([1, 3], [1, 1])
    assert np.isclose(low, 2 - 1.959964) and np.isclose(high, 2 + 1.959964)
    assert np.isnan(ratio_interval([1], [1])).all() and np.isnan(ratio_interval([1, 2], [0, 0])).all()


def test_crossing_snr_interpolates_between_grid_points():
    from experiments.compare import crossing_snr

    snr = np.array([10.0, 12.5, 15.0])
    # 90 % between 12.5 (86 %) and 15 dB (98 %): 12.5 + 2.5 (0.9 - 0.86) / (0.98 - 0.86).
    assert np.isclose(crossing_snr(snr, [0.5, 0.86, 0.98]), 12.5 + 2.5 / 3)
    assert crossing_snr(snr, [0.95, 0.99, 1.0]) == 10.0 and np.isnan(crossing_snr(snr, [0.1, 0.2, 0.3]))


def test_wilson_interval_matches_the_textbook_values():
    from experiments.compare import wilson

    low, high = wilson(np.array([0.0, 500.0]), np.array([1000.0, 1000.0]))
    # 0 of 1,000: the upper bound is z²/(n + z²) = 0.00383; 50 %: 0.469-0.531.
    assert np.allclose([low[0], high[0]], [0.0, 0.003827], atol=1e-5)
    assert np.allclose([low[1], high[1]], [0.469, 0.531], atol=1e-3)


def test_aggregating_a_directory_without_runs_is_one_line_and_exit_2(tmp_path, capsys):
    from experiments.aggregate import main

    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path / "empty"), "--out", str(tmp_path / "out")])
    assert exit_.value.code == 2
    assert capsys.readouterr().err == f"error: no trials.parquet below {tmp_path / 'empty'}\n"
    assert not (tmp_path / "out").exists()


def test_sweeps_without_a_name_get_directories_of_their_own():
    from harness_utils import compose_config

    unnamed = compose_config([], hydra=True).hydra.sweep.dir
    assert unnamed.startswith("outputs/sweeps/default/20") and len(unnamed) == len("outputs/sweeps/default/") + 19
    assert compose_config(["name=mine"], hydra=True).hydra.sweep.dir == "outputs/sweeps/mine"


def test_compare_skips_a_preset_whose_methods_are_not_installed(tmp_path, monkeypatch):
    import importlib.util

    from experiments import compare

    find_spec, ran = importlib.util.find_spec, []
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "clipperpy" else find_spec(name))
    monkeypatch.setattr(compare, "run_module", lambda argv: ran.append(argv[2]))
    with pytest.raises(FileNotFoundError):  # nothing ran, so no table to build
        compare.main(["--presets", "compare_clipper,compare_search,compare_teaser", "--out", str(tmp_path)])
    expected = ["experiment=compare_search"]
    if find_spec("teaserpp_python") is not None:
        expected.append("experiment=compare_teaser")
    assert ran == expected
