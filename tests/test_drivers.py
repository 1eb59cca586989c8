"""The benchmark and the wrong-σ driver, on tiny inputs: they run, and report what they measured."""

import pandas as pd
import pytest

from experiments import bench, sigma


def test_bench_times_a_merge_in_a_fresh_process_and_checks_its_sections():
    r = bench.fresh_process(300, "consensus")
    assert r["outcome"] == "done" and r["found"] and r["merge_s"] > 0 and r["peak_rss_gb"] > 0
    assert r["correct_pairs"] >= 200 and r["wrong_pairs"] <= 5
    assert 0 < bench.delaunay_floor(10, 0.75, 50) < 0.01
    with pytest.raises(SystemExit, match=r"--only: unknown section\(s\) \['grid'\]; allowed: per_trial"):
        bench.main(["--only", "grid"])


def test_sigma_driver_writes_its_table(tmp_path):
    sigma.main(["--trials", "2", "--out", str(tmp_path)])
    table = pd.read_csv(tmp_path / "table.csv")
    assert len(table) == len(sigma.SNRS) * 2 * len(sigma.FACTORS)
    told_truth = table[(table.method == "consensus") & (table.sigma_factor == 1.0)]
    assert (told_truth.success_rate == 1.0).all() and (told_truth.false_merges == "0 / 2").all()
