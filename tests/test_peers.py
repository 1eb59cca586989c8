"""The outside peers (mapmerge.baselines: cpd, clipper, teaser) on a few fixed pairs; skipped when absent."""

import sys

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import metrics
from mapmerge.baselines import associations

PEERS = [("cpd", "pycpd", 10), ("clipper", "clipperpy", 20), ("teaser", "teaserpp_python", 20)]


@pytest.mark.parametrize("method, module, n", PEERS)
def test_peer_finds_the_transform_and_rejects_unrelated_maps(method, module, n):
    pytest.importorskip(module)
    sc = mm.simulate.make_pair(n, 0.75, 35, rng=1)
    err = metrics.map_errors(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method=method))
    assert err["transform_found"] and err["wrong_pairs"] == 0 and err["correct_pairs"] >= n // 2
    other = mm.simulate.make_pair(n, 0.75, 35, rng=1, unrelated=True)
    assert not mm.merge_maps(other.p, other.q, other.sigma, method=method).matched


@pytest.mark.parametrize("method, module", [("clipper", "clipperpy"), ("teaser", "teaserpp_python")])
def test_peer_on_gated_associations(method, module):
    pytest.importorskip(module)
    # 60 x 60 landmarks is past the all-to-all limit: the signature gating feeds the peer.
    sc = mm.simulate.make_pair(60, 0.75, 35, rng=4)
    assert len(sc.p) * len(sc.q) > associations.ALL_TO_ALL_MAX
    assert metrics.map_errors(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method=method))["transform_found"]


@pytest.mark.parametrize("method, module, hint", [("cpd", "pycpd", "mapmerge[peers]"),
                                                  ("clipper", "clipperpy", "tools/build_peers.sh"),
                                                  ("teaser", "teaserpp_python", "tools/build_peers.sh")])
def test_missing_peer_names_how_to_install_it(monkeypatch, method, module, hint):
    monkeypatch.setitem(sys.modules, module, None)  # an import of it now fails
    sc = mm.simulate.make_pair(10, 0.75, 30, rng=0)
    with pytest.raises(ImportError, match=hint.replace("[", r"\[").replace("]", r"\]")):
        mm.merge_maps(sc.p, sc.q, sc.sigma, method=method)


def test_putative_associations_all_to_all_then_gated():
    rng = np.random.default_rng(0)
    P, Q = rng.uniform(0, 10, (5, 2)), rng.uniform(0, 10, (7, 2))
    A = associations.putative_associations(P, Q)
    assert len(A) == 35 and len(np.unique(A, axis=0)) == 35
    big_p, big_q = rng.uniform(0, 10, (80, 2)), rng.uniform(0, 10, (70, 2))
    G = associations.putative_associations(big_p, big_q)
    assert G.shape == (80 * associations.GATE_K, 2)
    assert np.array_equal(np.bincount(G[:, 0]), np.full(80, associations.GATE_K))
    # A landmark's own copy (the same map moved rigidly) is among its gated candidates.
    c, s = np.cos(1.0), np.sin(1.0)
    moved = big_p @ np.array([[c, s], [-s, c]]) + 3.0
    own = associations.putative_associations(big_p, moved)
    assert np.all((own[:, 0] == own[:, 1]).reshape(80, -1).any(axis=1))


def test_one_to_one_keeps_the_first_pair_of_each_landmark():
    pairs = np.array([[3, 1], [0, 1], [3, 2], [2, 0], [1, 4]])
    np.testing.assert_array_equal(associations.one_to_one(pairs), [[1, 4], [2, 0], [3, 1]])


def test_equal_rate_bound_lets_through_at_most_its_share_of_tuning_pairs():
    import pandas as pd

    from experiments import peers

    def rows(kind, pairs, found=None):
        found = [False] * len(pairs) if found is None else found
        return pd.DataFrame({"method": "clipper", "layout": "strip", "n_landmarks": 10, "snr_db": 20.0, "kind": kind,
                             "seed": range(len(pairs)), "merged": [k >= 3 for k in pairs], "found": found,
                             "pairs": pairs})

    # 1,000 tuning pairs at 1e-3: one may pass, so the bound is one above the second-largest count (7).
    tuning = [3] * 997 + [5, 7, 9]
    table = peers.equal_rate_table(pd.concat([
        rows("tuning", tuning), rows("related", [8, 8, 7, 2, 9], [True, False, True, False, True]),
        rows("unrelated", [8, 4, 0, 7, 3])]), {("strip", 10, 20.0): 0.6})
    row = table.iloc[0]
    assert row.bound == 8
    assert (row.found, row.wrong_merges, row.false_merges) == (2, 1, 1)
    shipped = peers.clipper.CLIPPER_MIN_INLIERS[10]
    assert row.shipped_bound == shipped
    assert row.shipped_false_merges == sum(k >= shipped for k in [8, 4, 0, 7, 3])


def test_one_bound_is_the_largest_cell_bound_of_the_size():
    import pandas as pd

    from experiments import peers

    def rows(snr, kind, pairs, found=None):
        found = [False] * len(pairs) if found is None else found
        return pd.DataFrame({"method": "cpd", "layout": "strip", "n_landmarks": 10, "snr_db": snr, "kind": kind,
                             "seed": range(len(pairs)), "merged": True, "found": found, "pairs": pairs})

    # Cell bounds 8 (10 dB: two tuning pairs reach 7) and 4 (20 dB): one bound of 8 for both cells.
    table = peers.one_bound_table(pd.concat([
        rows(10.0, "tuning", [3] * 998 + [7, 7]), rows(20.0, "tuning", [3] * 999 + [4]),
        rows(10.0, "related", [8, 6], [True, True]), rows(10.0, "unrelated", [2, 3]),
        rows(20.0, "related", [9, 6, 5, 8], [True, True, False, False]), rows(20.0, "unrelated", [5, 8, 1, 0])]))
    cells = table.set_index(["snr_from", "snr_db"])
    cell = cells.loc[10.0, 20.0]
    assert (cell.bound, cell.bound_cell, cell.cell_bound) == (8, "strip 10 dB", 4)
    assert (cell.found_rate, cell.wrong_merges, cell.false_merges) == (0.25, 1, 1)
    assert (cell.cell_found_rate, cell.cell_wrong_merges, cell.cell_false_merges) == (0.5, 2, 2)
    assert cells.loc[10.0, 10.0].found_rate == 0.5
    # From 15 dB the 10 dB cell neither sets the bound nor gets a row.
    assert len(table[table.snr_from == 15.0]) == 1
    assert (cells.loc[15.0, 20.0].bound, cells.loc[15.0, 20.0].found_rate) == (4, 0.5)


def test_a_rerun_of_some_methods_keeps_the_other_methods_rows(tmp_path):
    import pandas as pd

    from experiments import peers

    path = tmp_path / "peers.csv"
    pd.DataFrame({"method": ["consensus", "cpd", "consensus", "cpd"],
                  "layout": ["strip", "strip", "interleaved", "interleaved"],
                  "n_landmarks": 10}).to_csv(path, index=False)
    kept = peers.kept_rows(path, "strip", ["consensus"])
    assert sorted(zip(kept["method"], kept["layout"])) == [("consensus", "interleaved"), ("cpd", "interleaved"),
                                                           ("cpd", "strip")]


def test_equal_rate_chunks_are_kept_and_read_back(tmp_path, monkeypatch):
    from experiments import peers

    monkeypatch.setattr(peers, "EQUAL_RATE_ROWS", tmp_path)
    job = ("consensus", "strip", 10, 30, "related", 0, 4)
    first = peers.outcome_chunk(job)
    assert peers.chunk_path(job).is_file() and not list(tmp_path.glob("*.part"))
    assert len(first) == 4 and first["found"].any()
    assert peers.outcome_chunk(job).equals(first)


@pytest.mark.parametrize("method, module", [("cpd", "pycpd"), ("clipper", "clipperpy"), ("teaser", "teaserpp_python")])
def test_a_peers_kept_chunks_are_keyed_by_every_source_it_runs(tmp_path, monkeypatch, method, module):
    pytest.importorskip(module)
    from pathlib import Path

    from experiments import peers

    library = Path(mm.__file__).resolve().parent
    ran = set()

    def profile(frame, event, arg):
        path = Path(frame.f_code.co_filename)
        if path.is_relative_to(library):
            ran.add(path.relative_to(library))

    monkeypatch.setattr(peers, "EQUAL_RATE_ROWS", tmp_path)
    sys.setprofile(profile)
    try:
        for kind in ("related", "unrelated"):
            peers.outcome_chunk((method, "strip", 10, 20, kind, 0, 2))
    finally:
        sys.setprofile(None)
    assert {Path("simulate.py"), Path("merging.py"), Path("baselines") / f"{method}.py"} <= ran
    assert ran <= set(peers.peer_sources(method))
    # consensus's own stages are not among them, so a change there keeps the peers' chunks.
    assert not {"consensus.py", "search.py", "exhaustive.py", "association.py"} & set(peers.PEER_SOURCES)


def test_clipper_draws_its_start_from_the_merge_generator():
    pytest.importorskip("clipperpy")
    from mapmerge.baselines import clipper

    # CLIPPER's own start (std::random_device) moved 9 of 100 such inlier counts between two runs.
    scenes = [mm.simulate.make_pair(10, 0.75, 20.0, rng=seed, unrelated=True) for seed in range(40)]
    first = [clipper.clipper_pairs(sc.p, sc.q, sc.sigma) for sc in scenes]
    assert all(np.array_equal(a, clipper.clipper_pairs(sc.p, sc.q, sc.sigma)) for a, sc in zip(first, scenes))
    # A merge of several pairs gives each pair what a merge of it alone gives.
    P, Q, sigma = (np.stack([getattr(sc, k) for sc in scenes[:3]]) for k in ("p", "q", "sigma"))
    batch = mm.merge_batch(P, Q, sigma, method="clipper")
    for b, sc in enumerate(scenes[:3]):
        alone = mm.merge_maps(sc.p, sc.q, sc.sigma, method="clipper")
        np.testing.assert_array_equal(batch.result(b).pairs, alone.pairs)


def test_calibrating_one_peer_keeps_the_other_peers_rows(tmp_path, monkeypatch):
    pytest.importorskip("clipperpy")
    import pandas as pd

    from experiments import peers

    pd.DataFrame({"peer": ["cpd", "clipper", "cpd"], "n_landmarks": [100, 10, 10], "pairs": 9,
                  "max_share": 0.9}).to_csv(tmp_path / "calibration.csv", index=False)
    monkeypatch.setattr(peers, "CALIBRATION_PAIRS", {10: 4})
    monkeypatch.setattr(peers, "CELL_ROWS", tmp_path / "kept")
    df = peers.calibrate(tmp_path, 1, ["clipper"])
    assert list(zip(df["peer"], df["n_landmarks"], df["pairs"])) == [("cpd", 100, 9), ("cpd", 10, 9),
                                                                      ("clipper", 10, 4)]
    assert pd.read_csv(tmp_path / "calibration.csv")["peer"].tolist() == ["cpd", "cpd", "clipper"]


def test_a_cell_counts_landmark_pairs_against_the_oracle(tmp_path):
    import pandas as pd

    from experiments import peers

    row = peers.measure_cell(("consensus", "strip", 10, 40.0, 4))
    # At 40 dB consensus finds these pairs with every declared landmark pair right.
    assert row["found"] == 4 and row["wrong_pairs"] == 0
    assert 0 < row["correct_pairs"] <= row["common_pairs"]
    df = pd.DataFrame([{**row, "found_rate": 1.0, "found_lo": 0.5, "found_hi": 1.0, "false_merges": 0,
                        "correspondence_oracle_found": 1.0, "oracle_pairs": 4, "detector_found": float("nan")}])
    df["method"] = pd.Categorical(df["method"], ["consensus"])
    peers.write_markdown(df, tmp_path / "peers.md")
    share = 100 * row["correct_pairs"] / row["common_pairs"]
    assert f"| strip, 10, 40 dB | {share:.0f} % correct, 0.0 wrong |" in (tmp_path / "peers.md").read_text()


def test_a_cells_row_is_kept_and_read_back(tmp_path, monkeypatch):
    from experiments import peers

    monkeypatch.setattr(peers, "CELL_ROWS", tmp_path)
    job = ("paper", "strip", 10, 30, 3)
    first = peers.run_cell(job)
    assert peers.cell_path(job).is_file() and not list(tmp_path.glob("*.part"))
    monkeypatch.setattr(mm.simulate, "make_pairs", lambda *a, **k: pytest.fail("a kept cell was measured again"))
    assert peers.run_cell(job) == first


def test_fewer_pairs_by_map_size_and_snr():
    from experiments import peers

    table = {("teaser", 100): 500, ("teaser", 100, 0): 0}
    assert peers.fewer_pairs(table, "teaser", 100, 0, 1000) == 0
    assert peers.fewer_pairs(table, "teaser", 100, 10, 1000) == 500
    assert peers.fewer_pairs(table, "teaser", 100, 10, 200) == 200
    assert peers.fewer_pairs(table, "clipper", 100, 0, 1000) == 1000
    jobs = peers.equal_rate_jobs(["teaser", "clipper"], 1000, [("strip", 100, 0)])
    assert {j[0] for j in jobs} == {"clipper"}
