"""The benchmark, the wrong-σ driver and the detector's resume, on tiny inputs: they run, and
report what they measured."""

import numpy as np
import pandas as pd
import pytest

from experiments import bench, sigma


def test_bench_times_a_merge_in_a_fresh_process_and_checks_its_sections():
    r = bench.fresh_process(300, "consensus")
    assert r["outcome"] == "done" and r["found"] and r["merge_s"] > 0 and r["peak_rss_gb"] > 0
    assert r["correct_pairs"] >= 200 and r["wrong_pairs"] <= 5
    assert np.isfinite(bench.delaunay_floor(10, 0.75, 5)) and bench.delaunay_floor(10, 0.75, 5) > 0
    with pytest.raises(SystemExit, match=r"--only: unknown section\(s\) \['grid'\]; allowed: per_trial"):
        bench.main(["--only", "grid"])


def test_sigma_driver_writes_its_table(tmp_path):
    sigma.main(["--trials", "2", "--out", str(tmp_path)])
    table = pd.read_csv(tmp_path / "table.csv")
    assert len(table) == len(sigma.SNRS) * 2 * len(sigma.FACTORS)
    told_truth = table[(table.method == "consensus") & (table.sigma_factor == 1.0)]
    assert (told_truth.success_rate == 1.0).all() and (told_truth.false_merges == "0 / 2").all()


def test_detector_recomputes_the_pairs_other_code_wrote(tmp_path, monkeypatch):
    from experiments import detector

    calls = []

    def fake_measure(n, layout, snr, seed, unrelated):
        calls.append(seed)
        return (float(seed % 97) + snr, not unrelated, 0.0)

    monkeypatch.setattr(detector, "MEASURES", ((fake_measure, ("log_lr", "found", "seconds")),))
    monkeypatch.setattr(detector, "COLUMNS", [*detector.JOB, "log_lr", "found", "seconds", detector.CODE])
    path = tmp_path / "pairs.csv"
    fresh = detector.run_pairs(8, 1, path, (0.0,), ("strip",))
    assert len(calls) == 16 and set(fresh.code) == {detector.code_key()}
    # Rows another version wrote (their values may differ) are computed again; this code's are kept.
    stale = pd.read_csv(path)
    stale.loc[:4, "code"] = "0123456789ab"
    stale.loc[:4, "log_lr"] = -1.0
    stale.to_csv(path, index=False)
    calls.clear()
    pd.testing.assert_frame_equal(detector.run_pairs(8, 1, path, (0.0,), ("strip",)), fresh)
    assert len(calls) == 5
    # A file from before rows carried their code: every row is computed again.
    pd.read_csv(path).drop(columns="code").to_csv(path, index=False)
    calls.clear()
    pd.testing.assert_frame_equal(detector.run_pairs(8, 1, path, (0.0,), ("strip",)), fresh)
    assert len(calls) == 16
