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


def test_small_maps_acceptance_check_records_the_triangle_test_of_each_pair(tmp_path, monkeypatch):
    import mapmerge as mm
    from experiments import detector, small_maps

    monkeypatch.setattr(small_maps, "ROWS", tmp_path)
    search = mm.search.search_pairs
    row = small_maps.acceptance_table(10, "strip", 30.0, 6, 4, 3)
    assert mm.search.search_pairs is search
    assert (row["tuning_pairs"], row["related_pairs"], row["holdout_pairs"]) == (6, 4, 3)
    passes = [row[f"tuning_pass_{level:g}"] for level in small_maps.NFA_LEVELS]
    assert passes == sorted(passes) and 0 <= row["holdout_false_merges"] <= 3
    assert row["match_nfa"] == mm.consensus.match_level(10) and row["tuning_pass_shipped"] in passes
    for level in small_maps.NFA_LEVELS:
        assert 0 <= row[f"found_{level:g}"] + row[f"wrong_{level:g}"] <= 1
    # The batch's recorded NFA of a pair is the one the detector records when it merges that pair alone.
    rows = pd.read_csv(next(tmp_path.glob("acceptance_10_strip_30_*.csv")))
    related = rows[rows.kind == "related"].iloc[0]
    alone = detector.consensus_outcome(10, "strip", 30.0, int(related.seed), False)
    assert related.tri_log_nfa == pytest.approx(alone[4], rel=1e-9) and related.tri_found == alone[7]
    # Beyond HOLDOUT_MAX_LANDMARKS no held-out pair is merged.
    monkeypatch.setattr(small_maps, "HOLDOUT_MAX_LANDMARKS", 5)
    assert small_maps.acceptance_table(10, "strip", 30.0, 2, 1, 3)["holdout_pairs"] == 0


def test_small_maps_calibrated_check_loosens_the_triangle_test_and_restores_it(tmp_path):
    from mapmerge import consensus
    from experiments import small_maps

    default = consensus.MATCH_NFA
    # A tuning table whose quantile is a known log NFA: exp(-1) is looser than the default.
    tuning = pd.DataFrame({"n_landmarks": 10, "snr_db": 30.0, "unrelated": True, "tri_log_nfa": np.full(50, -1.0)})
    row = small_maps.calibrated_table(10, 30.0, 3, 4, 0.5, tuning, tmp_path)
    assert consensus.MATCH_NFA == default
    assert row["tri_log_nfa_threshold"] == -1.0 and row["related_pairs"] == 3 and row["holdout_pairs"] == 4
    assert 0 <= row["wrong_merges"] <= 3 and 0 <= row["false_merges"] <= 4
    cached = list(tmp_path.glob("calibrated_10_30_0.5_*.csv"))
    assert len(cached) == 1 and small_maps.calibrated_table(10, 30.0, 3, 4, 0.5, tuning, tmp_path) == row
    with small_maps.triangle_acceptance(1.0):
        assert consensus.match_level(10) == consensus.match_level(1000) == 1.0
    assert consensus.MATCH_NFA == default


def test_small_maps_levels_check_merges_more_at_a_looser_level_and_restores_it():
    from mapmerge import consensus
    from experiments import small_maps

    default = consensus.MATCH_NFA
    strict, loose = (small_maps.level_table(10, "strip", 20.0, level, 12, 3) for level in (1e-4, 1e-2))
    assert consensus.MATCH_NFA == default
    assert strict["related_pairs"] == loose["related_pairs"] == 12 and strict["holdout_pairs"] == 3
    merged = [row["found_rate"] * 12 + row["wrong_merges"] for row in (strict, loose)]
    # On 10-landmark maps at 20 dB the shipped level accepts few related pairs; 1e-2 accepts more of the same.
    assert merged[1] > merged[0]
    assert 0 <= strict["false_merges"] <= 3 and strict["false_upper"] > 0


def test_small_maps_reference_puts_consensus_beside_the_best_peer_and_the_detector():
    from experiments import small_maps

    def row(method, found, lo, hi, pairs=1000):
        return {"layout": "strip", "n_landmarks": 10, "snr_db": 20.0, "method": method, "pairs": pairs,
                "found_rate": found, "found_lo": lo, "found_hi": hi, "false_merges": 0,
                "correspondence_oracle_found": 0.6}

    peers = pd.DataFrame([row("consensus", 0.40, 0.37, 0.43), row("cpd", 0.53, 0.49, 0.57, 500),
                          row("clipper", 0.40, 0.37, 0.43), {**row("consensus", 1.0, 0.99, 1.0), "n_landmarks": 100}])
    limit = pd.DataFrame({"layout": ["strip"], "n_landmarks": [10], "snr_db": [20.0], "found_rate": [0.2],
                          "consensus_found_rate": [0.4]})
    count = pd.DataFrame({"layout": ["strip"], "n_landmarks": [10], "snr_db": [20.0], "found_rate": [0.45],
                          "found_lo": [0.42], "found_hi": [0.48], "false_merges": [1], "holdout_pairs": [10000]})
    # CPD with one bound per size finds less than CLIPPER, which that table lacks: CLIPPER at its cell rate.
    one_bound = pd.DataFrame({"method": "cpd", "layout": "strip", "n_landmarks": 10, "snr_db": 20.0,
                              "snr_from": [10.0, 15.0], "found_rate": [0.30, 0.50], "found_lo": [0.26, 0.46],
                              "found_hi": [0.34, 0.54]})
    table = small_maps.reference_table(peers, limit, count, one_bound)
    assert len(table) == 1  # 100 landmarks are not a small map
    r = table.iloc[0]
    assert (r.best_peer, r.peer_pairs, r.vs_peer) == ("cpd", 500, "behind")
    assert r.ratio_to_peer == pytest.approx(0.40 / 0.53) and r.ratio_to_detector == pytest.approx(2.0)
    assert (r.default_found, r.default_holdout_false, r.default_vs_peer) == (0.45, 1, "behind")
    assert (r.one_bound_peer_from_10db, r.one_bound_peer_found_from_10db,
            r.default_vs_one_bound_peer_from_10db) == ("clipper (cell)", 0.40, "level")
    assert (r.one_bound_peer_from_15db, r.default_vs_one_bound_peer_from_15db) == ("cpd (one bound)", "level")


def test_small_maps_statistics_check_holds_each_statistic_to_the_tuning_rate(tmp_path, monkeypatch):
    from experiments import small_maps

    monkeypatch.setattr(small_maps, "ROWS", tmp_path)
    peers = pd.DataFrame([{"layout": "strip", "n_landmarks": 10, "snr_db": 20.0, "method": method, "pairs": 500,
                           "found_rate": found, "found_lo": found - 0.05, "found_hi": found + 0.05}
                          for method, found in (("consensus", 0.4), ("cpd", 0.5), ("teaser", 0.45))])
    frames = small_maps.statistics_frames(10, "strip", 20.0, 40, 12, 20)
    assert [len(f) for f in frames] == [40, 12, 20]
    level = small_maps.size_level([frames])
    # The size's level lets at most SIZE_ALLOWED tuning pairs through (its only cell here).
    assert np.sum(frames[0].tri_log_count_nfa < level) <= small_maps.SIZE_ALLOWED
    row = small_maps.statistics_table(10, "strip", 20.0, frames, 0.1, level, peers)
    assert (row["tuning_pairs"], row["allowed"], row["related_pairs"]) == (40, 4, 12)
    assert row["size_level_tuning_pass"] <= small_maps.SIZE_ALLOWED
    for name in (*small_maps.RANKINGS, "size_level"):
        # Nothing passes that the triangles did not get right; the interval holds the rate.
        assert 0 <= row[f"{name}_holdout_false"] <= 20 and row[f"{name}_found"] <= row["ceiling"]
        assert row[f"{name}_lo"] <= row[f"{name}_found"] <= row[f"{name}_hi"]
    for name in small_maps.RANKINGS:
        assert row[f"{name}_tuning_pass"] <= 4
    assert row["shipped_found"] <= row["ceiling"] and row["best_peer"] == "cpd" and row["peer_found"] == 0.5
    assert row["count_first_vs_peer"] in ("ahead", "level", "behind")
    assert len(list(tmp_path.glob("statistics_10_strip_20_*.csv"))) == 1
    # Kept rows are read back: the same row, and without a cell in the peers' table no peer.
    again = small_maps.statistics_table(10, "strip", 20.0, small_maps.statistics_frames(10, "strip", 20.0, 40, 12, 20),
                                        0.1, level, peers.iloc[:0])
    assert again["nfa_found"] == row["nfa_found"] and again["count_first_vs_peer"] == "n/a"


def test_small_maps_count_check_runs_consensus_count_beside_consensus_and_the_peer():
    from mapmerge import consensus
    from experiments import small_maps

    peers = pd.DataFrame([{"layout": "strip", "n_landmarks": 10, "snr_db": 20.0, "method": method, "pairs": 500,
                           "found_rate": found, "found_lo": found - 0.05, "found_hi": found + 0.05}
                          for method, found in (("consensus", 0.4), ("cpd", 0.5))])
    row = small_maps.count_table(10, "strip", 20.0, 12, 3, peers)
    assert row["log_level"] == pytest.approx(consensus.COUNT_LEVELS[10])
    assert (row["related_pairs"], row["holdout_pairs"], row["best_peer"]) == (12, 3, "cpd")
    assert row["consensus_lo"] <= row["consensus_found"] <= row["consensus_hi"] and 0 <= row["consensus_wrong"] <= 12
    assert row["vs_consensus"] in ("ahead", "level", "behind")
    assert 0 <= row["wrong_over_5_deg"] <= row["wrong_merges"] and 0 <= row["consensus_wrong_over_5_deg"] <= 12
    assert 0 <= row["wrong_oracle_found"] <= min(row["wrong_merges"], row["oracle_found"]) <= 12
    assert 0 <= row["consensus_wrong_oracle_found"] <= row["consensus_wrong"]
    assert row["search_log_level"] == consensus.SEARCH_COUNT_LEVELS[10]
    assert row["found_lo"] <= row["found_rate"] <= row["found_hi"] and 0 <= row["false_merges"] <= 3
    # The levels check at consensus's own level counts the same pairs the same way.
    shipped = small_maps.level_table(10, "strip", 20.0, consensus.match_level(10), 12, 3)
    assert (shipped["found_rate"], shipped["wrong_merges"]) == (row["consensus_found"], row["consensus_wrong"])


def test_small_maps_oracle_count_accepts_the_true_transform_where_it_is_plain_and_rarely_where_not():
    """At 20 landmarks and 30 dB the count test accepts the association at the true transform on every pair,
    as consensus_count finds them; at 10 landmarks and 15 dB on few."""
    from experiments import small_maps

    plain = small_maps.oracle_count_table(20, "strip", 30.0, 10)
    assert plain["found_rate"] == plain["oracle_accepted_rate"] == 1.0 and plain["search_log_level"] < -30
    hard = small_maps.oracle_count_table(10, "strip", 15.0, 30)
    assert hard["oracle_accepted_rate"] <= 0.5 and hard["found_rate"] <= 0.5


def test_small_maps_count_levels_spend_the_search_merges_first(tmp_path, monkeypatch):
    from experiments import small_maps
    from mapmerge import consensus

    monkeypatch.setattr(small_maps, "ROWS", tmp_path)
    monkeypatch.setattr(consensus, "TUNING_ALLOWED", 2)
    monkeypatch.setattr(consensus, "SEARCH_ALLOWED", 1)
    frames = small_maps.count_level_frames(10, "strip", 20.0, 30)
    assert len(frames[0]) == len(frames[1]) == 30 and (frames[0].seed.to_numpy() == frames[1].seed.to_numpy()).all()
    assert np.isfinite(frames[1].log_count_nfa).any()
    assert len(list(tmp_path.glob("search_10_strip_20_*.csv"))) == 1

    def cell(counts, merged, search_counts):
        return (pd.DataFrame({"tri_log_count_nfa": counts}),
                pd.DataFrame({"merged": merged, "log_count_nfa": search_counts}))

    table = small_maps.count_level_table({
        (10, "strip", 20.0): cell([-9.0, -5.0, -4.0, -1.0, 0.0], [False, True, False, False, False],
                                  [np.inf, -30.0, -2.0, -1.0, np.inf]),
        (10, "strip", 30.0): cell([-8.0, -7.5, -3.0, 2.0], [False] * 4, [-6.0, -9.0, np.inf, -5.0]),
        (20, "strip", 20.0): cell([-1.0, 1.0, 2.0], [True, True, False], [0.0, 0.0, 0.0]),
        (20, "strip", 30.0): cell([-2.0, 3.0, 5.0], [True, True, True], [0.0, 0.0, 0.0])})
    # The search, one allowed a cell: at 20 dB its own test spends it, so -2 must stop; at 30 dB -9 may
    # merge and -6 must stop. The size's search level is just below the lower limit, and merges one pair
    # in each cell (the second: by its own test at 20 dB, by its count at 30 dB).
    assert table.search_limit.tolist()[:2] == [-2.0, -6.0] and (table.search_log_level[:2] == -6.01).all()
    assert table.search_merges.tolist()[:2] == [1, 1]
    # Triangles, two allowed: each cell has spent one on the search, so 20 dB stops -4 (-9 may merge) and
    # 30 dB stops -3 (-8 may merge); the level is just below the lower, and lets two through in each.
    assert table.cell_limit.tolist()[:2] == [-4.0, -3.0] and (table.log_level[:2] == -4.01).all()
    assert table.tuning_merges.tolist()[:2] == [2, 2]
    # 20 landmarks: the search's own test exceeds its allowance in both cells, so its count may add none: at
    # 20 dB it must stop its one pair left (0), at 30 dB it has none left. The triangle test likewise: at
    # 20 dB it must stop its one pair left (2), and the search's two merges are all the cell lets through.
    assert table.search_limit.tolist()[2:] == [0.0, np.inf] and (table.search_log_level[2:] == -0.01).all()
    assert table.search_merges.tolist()[2:] == [2, 3]
    assert table.cell_limit.tolist()[2:] == [2.0, np.inf] and (table.log_level[2:] == 1.99).all()
    assert table.tuning_merges.tolist()[2:] == [2, 3]
