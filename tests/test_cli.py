"""The mapmerge command and the map-file reader, end to end on files written here."""

import json
import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

import mapmerge as mm
from mapmerge.cli import main


def _maps(tmp_path, rotation_deg=30.0, sigma=0.02, seed=3):
    """Two maps of 30 landmarks, 20 shared, q rotated and shifted; ids name the landmarks."""
    rng = np.random.default_rng(seed)
    world = rng.uniform(0, 6, (40, 2))
    th = np.radians(rotation_deg)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    p = world[:30] + rng.normal(0, sigma, (30, 2))
    q = world[10:] @ R.T + [1.0, 2.0] + rng.normal(0, sigma, (30, 2))
    a, b = tmp_path / "a.csv", tmp_path / "b.tsv"
    pd.DataFrame({"id": [f"L{i}" for i in range(30)], "x": p[:, 0], "y": p[:, 1]}).to_csv(a, index=False)
    pd.DataFrame({"id": [f"L{i}" for i in range(10, 40)], "x": q[:, 0], "y": q[:, 1]}).to_csv(b, index=False, sep="\t")
    return a, b, th


def test_merge_writes_the_combined_map_and_a_json_summary(tmp_path, capsys):
    a, b, th = _maps(tmp_path)
    out, plot = tmp_path / "merged.csv", tmp_path / "merged.png"
    assert main(["merge", str(a), str(b), "--sigma", "0.02", "-o", str(out), "--plot", str(plot), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["matched"] and info["pairs"] == 20 and info["second_match"] is None
    assert abs(info["theta"] - th) < 3 * info["theta_std"] + 1e-9
    np.testing.assert_allclose(info["t"], [1.0, 2.0], atol=5 * max(info["t_std"]))
    merged = pd.read_csv(out)
    fused = merged[merged.origin == "fused"]
    assert len(merged) == 40 and len(fused) == 20
    assert (fused.id_p == fused.id_q).all()  # every fused row joins the same landmark
    assert {"x", "y", "origin", "index_p", "index_q", "sxx", "sxy", "syy"} <= set(merged.columns)
    assert plot.stat().st_size > 10_000
    # Written in full: the file reads back as the library's combined map, bit for bit.
    res = mm.merge_maps(mm.read_map(a).points, mm.read_map(b).points, 0.02)
    np.testing.assert_array_equal(merged[["x", "y"]].to_numpy(), res.merged)


def test_a_bent_map_merges_with_a_warning_naming_the_second_match(tmp_path, capsys):
    sc = mm.simulate.make_pair(200, 0.75, 30, rng=3)
    towards_overlap = sc.q[np.isin(sc.ids_q, sc.ids_p)].mean(axis=0) - sc.q.mean(axis=0)
    q = mm.simulate.bend(sc.q, np.radians(8.0), 0.4, towards_overlap)
    a, b, out = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "merged.csv"
    pd.DataFrame(sc.p, columns=["x", "y"]).to_csv(a, index=False)
    pd.DataFrame(q, columns=["x", "y"]).to_csv(b, index=False)
    assert main(["merge", str(a), str(b), "--sigma", str(sc.sigma), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning: the landmarks left unpaired hold a second rigid match" in err and "deg" in err
    assert main(["merge", str(a), str(b), "--sigma", str(sc.sigma), "-o", str(out), "--json"]) == 0
    second = json.loads(capsys.readouterr().out)["second_match"]
    assert second["pairs"] >= 20 and abs(abs(second["rotation_offset_deg"]) - 8.0) < 0.5


def test_unrelated_maps_exit_1_and_write_nothing(tmp_path, capsys):
    a, _, _ = _maps(tmp_path)
    rng = np.random.default_rng(9)
    other = tmp_path / "other.csv"
    pd.DataFrame(rng.uniform(0, 6, (30, 2)), columns=["x", "y"]).to_csv(other, index=False)
    out = tmp_path / "merged.csv"
    assert main(["merge", str(a), str(other), "--sigma", "0.02", "-o", str(out)]) == 1
    assert "no match" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("content, message", [
    ("x,z\n1,2\n3,4\n5,6\n", "missing column y"),
    ("x,y\n1,2\n3,oops\n5,6\n", "column y row 2 is 'oops'"),
    ("x,y\n1,2\n3,\n5,6\n", "column y row 2 is ''"),
    ("x,y\n1,2\nnan,4\n5,6\n", "column x row 2 is 'nan'"),
    ("x,y\n1,2\n3,4\n", "at least 3 landmarks"),
    ("x,y,sxx,sxy\n1,2,1,0\n3,4,1,0\n5,6,1,0\n", "needs all of sxx, sxy, syy"),
    ("x,y,sigma\n1,2,1\n3,4,0\n5,6,1\n", "sigma must be > 0"),
    # Beyond the range merge_maps takes (squares would overflow): one line, no numpy warning.
    ("x,y,sigma\n1,2,1\n3,4,1e300\n5,6,1\n",
     "bad.csv: row 2: sigma must lie in [1e-50, 1e+50] (rescale the map's units)"),
    ("x,y,sxx,sxy,syy\n1,2,1,0,1e120\n3,4,1,0,1\n5,6,1,0,1\n",
     "bad.csv: row 1: sxx and syy must lie in [1e-100, 1e+100]"),
    ("x,y\n1e60,0\n1,0\n0,1\n", "bad.csv: has coordinates of magnitude up to 1e+60; at most 1e+50 is allowed"),
    # Errors of the maps' geometry name the file, not the library's argument.
    ("x,y\n0,0\n1,1\n2,2\n", "bad.csv: points are all collinear"),
    ("x,y\n0,0\n1,0\n0,1\n1,0\n", "bad.csv: contains duplicate points"),
    ("id,x,y\nA,0,0\nB,1,0\nA,0,1\n", "bad.csv: id 'A' is repeated (rows 1 and 3)"),
    ("x;y\n0;0\n1;0\n0;1\n", "bad.csv: columns separated by ';'"),
    ("x,y,sxx,sxy,syy\n1,2,1,0,1\n3,4,1,2,1\n5,6,1,0,1\n",
     "bad.csv: row 2: covariance (sxx, sxy, syy) must be positive definite"),
    ("", "bad.csv: not a CSV/TSV table"),
    (b"\xff\xfex\x00,\x00y\x00", "bad.csv: not UTF-8 text (byte 0); save the map as UTF-8 CSV"),  # UTF-16
])
def test_bad_files_give_one_line_and_exit_2(tmp_path, capsys, content, message):
    a, _, _ = _maps(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_bytes(content) if isinstance(content, bytes) else bad.write_text(content)
    assert main(["merge", str(a), str(bad), "--sigma", "0.02", "-o", str(tmp_path / "m.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and not (tmp_path / "m.csv").exists()


@pytest.mark.parametrize("seed", ["-1", "x"])
def test_a_bad_seed_is_refused_by_the_parser(tmp_path, capsys, seed):
    a, b, _ = _maps(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(["merge", str(a), str(b), "--sigma", "0.02", "-o", str(tmp_path / "m.csv"), "--seed", seed])
    assert exit_.value.code == 2
    assert f"argument --seed: must be an integer >= 0, got '{seed}'" in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["-o", "{tmp}/no/such/dir/m.csv"], "--output: directory"),
    (["-o", "{tmp}/a.csv"], "--output: {tmp}/a.csv is an input map"),
    (["-o", "{tmp}/m.csv", "--plot", "{tmp}/m.txt"], "--plot: {tmp}/m.txt must end in one of"),
    (["-o", "{tmp}/m.xlsx"], "--output: {tmp}/m.xlsx must end in .csv, .tsv (tab-separated) or .txt"),
    (["-o", "{tmp}/m.csv", "--plot", "{tmp}/no/m.png"], "--plot: directory"),
])
def test_unwritable_outputs_are_refused_before_any_work(tmp_path, capsys, extra, message):
    a, b, _ = _maps(tmp_path)
    before = a.read_bytes()
    assert main(["merge", str(a), str(b), "--sigma", "0.02", *[e.format(tmp=tmp_path) for e in extra]]) == 2
    err = capsys.readouterr().err.strip()
    assert message.format(tmp=tmp_path) in err and "\n" not in err
    assert a.read_bytes() == before and not (tmp_path / "m.csv").exists()


def test_a_failed_write_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    import mapmerge.cli

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / "m.csv"))

    monkeypatch.setattr(mapmerge.cli, "write_map", refuse)
    a, b, _ = _maps(tmp_path)
    assert main(["merge", str(a), str(b), "--sigma", "0.02", "-o", str(tmp_path / "m.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"mapmerge: error: cannot write {tmp_path / 'm.csv'}: Permission denied"


def test_read_map_takes_a_dataframe_and_covariances():
    table = pd.DataFrame({"x": [0, 1, 0], "y": [0, 0, 1], "sxx": [1, 2, 3], "sxy": [0, 0.5, 0], "syy": [1, 2, 3]})
    m = mm.read_map(table)
    np.testing.assert_array_equal(m.points, [[0, 0], [1, 0], [0, 1]])
    np.testing.assert_array_equal(m.cov[1], [[2, 0.5], [0.5, 2]])
    np.testing.assert_array_equal(m.variances, [1, 2, 3])


def test_python_dash_m_runs_the_same_command(tmp_path):
    a, b, _ = _maps(tmp_path)
    out = tmp_path / "m.csv"
    proc = subprocess.run([sys.executable, "-m", "mapmerge", "merge", str(a), str(b), "--sigma", "0.02",
                           "-o", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0 and "matched (consensus_count)" in proc.stdout and out.exists()


def test_sigma_comes_from_the_maps_covariances_when_left_out(tmp_path, capsys):
    a, b, th = _maps(tmp_path)
    sd_p, sd_q = 0.015, 0.025  # per-landmark standard deviations the files state
    for path, sd, sep in ((a, sd_p, ","), (b, sd_q, "\t")):
        table = pd.read_csv(path, sep=sep)
        table["sigma"] = sd
        table.to_csv(path, index=False, sep=sep)
    out = tmp_path / "merged.csv"
    assert main(["merge", str(a), str(b), "-o", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["sigma"] == pytest.approx(np.sqrt((sd_p**2 + sd_q**2) / 2))  # 30 landmarks each
    assert info["matched"] and info["pairs"] == 20 and abs(info["theta"] - th) < 0.01
    # Without covariances the command needs --sigma, and says so.
    plain = tmp_path / "plain"
    plain.mkdir()
    a2, b2, _ = _maps(plain)
    assert main(["merge", str(a2), str(b2), "-o", str(out)]) == 2
    assert "--sigma is needed when the maps give no covariances" in capsys.readouterr().err


def test_merge_maps_pools_sigma_from_covariances_and_needs_one_or_the_other():
    sc = mm.simulate.make_pair(40, 0.75, 30, rng=5)
    cov_p, cov_q = np.full(40, sc.sigma**2), np.full(40, 4 * sc.sigma**2)
    res = mm.merge_maps(sc.p, sc.q, cov_p=cov_p, cov_q=cov_q)
    same = mm.merge_maps(sc.p, sc.q, np.sqrt(2.5) * sc.sigma, cov_p=cov_p, cov_q=cov_q)
    assert res.matched and np.array_equal(res.pairs, same.pairs)
    assert res.theta == pytest.approx(same.theta, abs=1e-12)
    with pytest.raises(ValueError, match="sigma is needed unless cov_p and cov_q"):
        mm.merge_maps(sc.p, sc.q, cov_p=cov_p)


def test_the_user_guides_worked_example_prints_what_it_says(tmp_path, capsys, monkeypatch):
    """docs/merging.md: its export snippet, command and Python lines, run as written, print and write what it shows."""
    import re
    from pathlib import Path

    guide = (Path(__file__).resolve().parents[1] / "docs" / "merging.md").read_text()
    api, export = re.findall(r"```python\n(.*?)```", guide, re.S)
    shown = re.search(r"\$ \.venv/bin/mapmerge (.*?)\n(.*?)```", guide, re.S)
    monkeypatch.chdir(tmp_path)
    exec(export, {})
    assert main(shown.group(1).split()) == 0
    assert capsys.readouterr().out == shown.group(2)
    merged = pd.read_csv("merged.csv")
    fused = merged[merged.origin == "fused"]
    assert merged.origin.value_counts().to_dict() == {"q": 76, "fused": 59, "p": 23}
    mismatched = fused.loc[fused.id_p != fused.id_q, ["id_p", "id_q"]].to_numpy().ravel()
    assert (fused.id_p == fused.id_q).sum() == 58 and set(mismatched) == {3, 19}
    by_cli = Path("merged.csv").read_bytes()
    namespace = {}
    exec(api, namespace)  # the Python lines write the same file
    assert Path("merged.csv").read_bytes() == by_cli
    # "--method paper on the same files pairs 71 landmarks with 29 conflicts and a rotation 5.2° away"
    assert main(["merge", "a.csv", "b.csv", "-o", "paper.csv", "--method", "paper", "--json"]) == 0
    paper = json.loads(capsys.readouterr().out)
    assert (paper["pairs"], paper["conflicts"]) == (71, 29)
    assert round(np.degrees(abs(paper["theta"] - namespace["res"].theta)), 1) == 5.2


def test_a_missing_map_file_is_one_line_and_exit_2(tmp_path, capsys):
    a, _, _ = _maps(tmp_path)
    assert main(["merge", str(a), str(tmp_path / "nowhere.csv"), "--sigma", "0.02", "-o", str(tmp_path / "m.csv")]) == 2
    assert capsys.readouterr().err.strip() == f"mapmerge: error: {tmp_path / 'nowhere.csv'}: no such file"


def test_a_map_saved_with_a_byte_order_mark_keeps_its_first_column(tmp_path):
    """Spreadsheets often save UTF-8 with a BOM: the first header (here ``id``) must still be recognised."""
    path = tmp_path / "bom.csv"
    path.write_bytes("id,x,y\nA,0,0\nB,1,0\nC,0,1\n".encode("utf-8-sig"))
    landmarks = mm.read_map(path)
    assert list(landmarks.ids) == ["A", "B", "C"] and landmarks.points.shape == (3, 2)


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out == f"mapmerge {mm.__version__}\n"


def test_write_map_names_what_is_not_the_merge_or_its_maps(tmp_path):
    a, b, _ = _maps(tmp_path)
    map_p, map_q = mm.read_map(a), mm.read_map(b)
    res = mm.merge_maps(map_p.points, map_q.points, 0.02)
    with pytest.raises(ValueError, match="result must be the MergeResult of merge_maps, got str"):
        mm.write_map("merged", tmp_path / "m.csv")
    with pytest.raises(ValueError, match="map_q must be the LandmarkMap .* merged as q, with at least 30 rows"):
        mm.write_map(res, tmp_path / "m.csv", map_p, mm.read_map(pd.read_csv(b, sep="\t").head(5)))
    assert pd.read_csv(mm.write_map(res, tmp_path / "m.csv", map_p, map_q)).id_q.notna().any()


def _scaled_maps(tmp_path, scale):
    a, b, _ = _maps(tmp_path)
    q = pd.read_csv(b, sep="\t")
    q[["x", "y"]] *= scale
    scaled = tmp_path / "b_scaled.csv"
    q.to_csv(scaled, index=False)
    return a, scaled


def test_maps_in_different_units_warn_and_strict_refuses(tmp_path, capsys):
    """Map b in millimetres, map a in metres: a warning saying by how much; --strict makes it exit 2."""
    a, b = _scaled_maps(tmp_path, 1000.0)
    args = ["merge", str(a), str(b), "--sigma", "0.02", "-o", str(tmp_path / "m.csv")]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert re.search(r"warning: map b's landmarks are spaced 1,\d{3}x map a's \(median nearest-neighbour "
                     r"distance \d+ against 0\.\d+\): are both in the same units\?", err)
    assert main([*args, "--strict"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mapmerge: error: map b's") and err[0].endswith("(refused: --strict)")
    # Within the factor: no warning (a's spacing against b's at 1.5x).
    a, b = _scaled_maps(tmp_path, 1.5)
    main(["merge", str(a), str(b), "--sigma", "0.02", "-o", str(tmp_path / "m.csv"), "--strict"])
    assert "warning" not in capsys.readouterr().err


def test_an_unexpected_error_is_one_bug_report_line_and_exit_3(tmp_path, capsys, monkeypatch):
    a, b, _ = _maps(tmp_path)

    def broken(*args, **kwargs):
        raise RuntimeError("something the code did not expect\nsecond line")

    monkeypatch.setattr(mm.cli, "merge_maps", broken)
    assert main(["merge", str(a), str(b), "--sigma", "0.02", "-o", str(tmp_path / "m.csv")]) == mm.cli.EXIT_BUG == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "internal error (RuntimeError: something the code did not expect)" in err
    assert "please report it" in err and "Traceback" not in err


def test_a_wrong_paper_merge_is_flagged_and_json_names_its_units(tmp_path, capsys):
    """On the paper's 100-landmark scenario ``paper`` pairs wrong landmarks (README): its pairs then
    disagree with its one rigid motion, which the command says; ``consensus`` on the same maps does not."""
    sc = mm.simulate.make_pair(100, 0.75, 30, rng=0)
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    pd.DataFrame(sc.p, columns=["x", "y"]).to_csv(a, index=False)
    pd.DataFrame(sc.q, columns=["x", "y"]).to_csv(b, index=False)
    args = ["merge", str(a), str(b), "--sigma", repr(sc.sigma), "-o", str(tmp_path / "m.csv"), "--json"]
    assert main([*args, "--method", "paper"]) == 0
    out, err = capsys.readouterr()
    info = json.loads(out)
    assert not info["rigid_check"]["agree"] and info["rigid_check"]["outliers"] >= 1
    assert "lie off its rigid motion, beyond the chi-square bound" in err and "paper has no acceptance test" in err
    assert info["warnings"] == [err.strip()[len("warning: "):]]
    assert main(args) == 0
    out, err = capsys.readouterr()
    info = json.loads(out)
    assert err == "" and info["warnings"] == [] and info["rigid_check"]["agree"]
    assert info["theta_deg"] == pytest.approx(np.degrees(info["theta"]))
    assert info["theta_std_deg"] == pytest.approx(np.degrees(info["theta_std"]))
    assert info["units"]["theta"] == "rad" and info["units"]["theta_deg"] == "deg" and info["units"]["t"] == "map units"


@pytest.mark.parametrize("value, std, text", [
    (-59.46648, 0.02521, "-59.466 ± 0.025"),
    (60.4123, 1.7, "60.4 ± 1.7"),
    (12.3456789, 0.00012, "12.34568 ± 0.00012"),  # a map in km, to 12 cm
    (123456.7, 1700.0, "123457 ± 1.7e+03"),
    (1234567.891234, 0.0123, "1234567.891 ± 0.012"),  # a map in µm-scale units
    (1.234567e48, 3e44, "1.23457e+48 ± 3.0e+44"),
    (-3.2e-20, 1e-24, "-3.20000e-20 ± 1.0e-24"),
    (2.5, 0.0, "2.5 ± 0"),
])
def test_numbers_are_printed_to_the_digits_their_uncertainty_supports(value, std, text):
    assert mm.cli.with_std(value, std) == text


def _team_files(tmp_path, n_strangers=1, **kwargs):
    team = mm.simulate.make_group(4, 60, 0.5, 25, topology="ring", n_strangers=n_strangers, rng=3, **kwargs)
    paths = []
    for k, m in enumerate(team.maps):
        paths.append(tmp_path / f"m{k}.csv")
        pd.DataFrame({"x": m[:, 0], "y": m[:, 1]}).to_csv(paths[-1], index=False)
    return team, [str(p) for p in paths]


def test_merge_of_many_files_writes_the_fused_map_and_names_the_map_left_out(tmp_path, capsys):
    team, paths = _team_files(tmp_path)
    out = tmp_path / "fused.csv"
    assert main(["merge", *paths, "--sigma", str(team.sigma), "-o", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    info = json.loads(captured.out)
    assert [m["placed"] for m in info["maps"]] == [True] * 4 + [False]
    assert info["maps"][4]["theta"] is None and "m4.csv matched no other map" in captured.err
    table = pd.read_csv(out)
    group = mm.merge_many(team.maps, team.sigma)
    assert len(table) == len(group.merged) == info["landmarks"]
    np.testing.assert_array_equal(table[[f"index_{k}" for k in range(5)]].to_numpy(), group.tracks)
    np.testing.assert_allclose(table[["x", "y"]].to_numpy(), group.merged, rtol=1e-15)
    assert (table.index_4 == -1).all() and (table.n_maps == (group.tracks >= 0).sum(axis=1)).all()


def test_merge_of_many_unrelated_files_is_no_match_and_writes_nothing(tmp_path, capsys):
    maps = [mm.simulate.make_group(2, 40, 0.5, 30, rng=k).maps[0] for k in range(3)]
    paths = []
    for k, m in enumerate(maps):
        paths.append(str(tmp_path / f"u{k}.csv"))
        pd.DataFrame({"x": m[:, 0], "y": m[:, 1]}).to_csv(paths[-1], index=False)
    out = tmp_path / "fused.csv"
    assert main(["merge", *paths, "--sigma", "0.05", "-o", str(out)]) == 1
    assert "no match: none of the 3 maps" in capsys.readouterr().err and not out.exists()


def test_merge_needs_two_files(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["merge", str(tmp_path / "a.csv"), "-o", str(tmp_path / "o.csv")])
    assert stop.value.code == 2 and "at least two map files" in capsys.readouterr().err
