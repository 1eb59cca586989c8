"""Property-based fuzzing of the map reader, ``merge_maps`` and the ``mapmerge merge`` command.

Whatever the files hold (maps of 3-2,000 landmarks, one map an affine
distortion of the other at a scale of 1e-30 to 1e30, duplicated and
nearly duplicated landmarks, a σ from 1e-60 to 1e60, random bytes), the
command must answer with exit status 0, 1 or 2 and one-line messages,
never a traceback or the bug-report status 3, and its memory must stay
within ``PEAK_BYTES``. The profile is derandomized (``derandomize=True``,
no example database), so every run, in CI too, tries the same examples.
"""

import contextlib
import io
import subprocess
import sys
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mapmerge as mm
from mapmerge import cli

#: Peak memory one merge of two maps of at most 2,000 landmarks may allocate (numpy's and Python's
#: allocations, as tracemalloc sees them), and the peak RSS of the whole command in a fresh process.
PEAK_BYTES = 1024 * 2**20
PEAK_RSS_BYTES = int(1.5 * 2**30)

FUZZ = settings(max_examples=20, derandomize=True, database=None, deadline=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# Mostly small maps (each example must be fast), one in ten up to 2,000 landmarks.
sizes = st.integers(0, 9).flatmap(lambda k: st.integers(300, 2000) if k == 0 else st.integers(3, 40))


@st.composite
def map_pairs(draw):
    """Two maps of one random world: q an affine image of p's landmarks (and its own), with extras."""
    n_p, n_q = draw(sizes), draw(sizes)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    shared = draw(st.integers(0, min(n_p, n_q)))
    world = rng.uniform(0, 10, (n_p + n_q - shared, 2))
    p = world[:n_p].copy()
    q = world[n_p - shared:].copy()
    # q in other units and a distorted frame: scale 1e-30..1e30, rotation, shear and stretch.
    scale = 10.0 ** draw(st.floats(-30, 30))
    phi = draw(st.floats(0, 2 * np.pi))
    shear = np.array([[1 + draw(st.floats(-0.9, 2)), draw(st.floats(-1, 1))], [0.0, 1 + draw(st.floats(-0.9, 2))]])
    A = scale * np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]]) @ shear
    q = q @ A.T + scale * draw(st.floats(-1e3, 1e3))
    noise = 10.0 ** draw(st.floats(-6, 0))
    p, q = p + rng.normal(0, noise, p.shape), q + rng.normal(0, noise * scale, q.shape)
    for m in (p, q):
        how = draw(st.sampled_from(["none", "none", "exact", "near", "offset"]))
        k = draw(st.integers(1, 3))
        rows = rng.integers(0, len(m), k)
        if how == "exact":  # a landmark written twice
            m[rows[1:] % len(m)] = m[rows[0]]
        elif how == "near":  # a landmark written twice, the copy off by one part in 10¹²
            m[(rows[0] + 1) % len(m)] = m[rows[0]] * (1 + 1e-12)
        elif how == "offset":  # the whole map far from its origin: near-duplicates in relative terms
            m += 10.0 ** draw(st.floats(0, 45))
    extent = float(np.ptp(p, axis=0).max()) or 1.0
    sigma = draw(st.one_of(st.floats(-60, 60).map(lambda e: 10.0**e),
                           st.floats(-8, 1).map(lambda e: extent * 10.0**e / np.sqrt(n_p))))
    return p, q, sigma


def _run(argv):
    """``mapmerge`` in this process: exit status, stdout, stderr and the peak traced allocation."""
    out, err = io.StringIO(), io.StringIO()
    tracemalloc.start()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = cli.main(argv)
            except SystemExit as exc:  # argparse
                code = exc.code
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return code, out.getvalue(), err.getvalue(), peak


def _assert_clean(code, err, peak):
    assert code in (0, 1, 2), err
    assert "Traceback" not in err and "internal error" not in err, err
    assert all(line.startswith(("mapmerge: error:", "warning:", "no match:", "usage:", "mapmerge merge:"))
               or line.startswith(" ") for line in err.splitlines()), err
    assert peak < PEAK_BYTES, f"{peak / 2**20:.0f} MiB"


@FUZZ
@given(map_pairs(), st.sampled_from(["consensus", "consensus", "search", "paper", "groth"]), st.booleans())
def test_any_two_maps_merge_or_are_refused_in_one_line(pair, method, strict):
    p, q, sigma = pair
    with tempfile.TemporaryDirectory() as tmp:
        a, b, out = Path(tmp, "a.csv"), Path(tmp, "b.csv"), Path(tmp, "merged.csv")
        pd.DataFrame(p, columns=["x", "y"]).to_csv(a, index=False)
        pd.DataFrame(q, columns=["x", "y"]).to_csv(b, index=False)
        argv = ["merge", str(a), str(b), "--sigma", repr(sigma), "-o", str(out), "--method", method, "--json"]
        code, stdout, err, peak = _run(argv + (["--strict"] if strict else []))
        _assert_clean(code, err, peak)
        assert out.exists() == (code == 0)
        # The library says the same: a result, or a one-line ValueError (the CLI's exit 2).
        try:
            res = mm.merge_maps(mm.read_map(a).points, mm.read_map(b).points, sigma, method=method)
        except ValueError as exc:
            assert code == 2 and "\n" not in str(exc)
        else:
            assert code == 2 or res.matched == (code == 0)


@FUZZ
@given(st.binary(max_size=3000), st.sampled_from(["a.csv", "a.tsv", "a.txt"]))
def test_random_bytes_as_a_map_file_are_refused_in_one_line(data, name):
    with tempfile.TemporaryDirectory() as tmp:
        a, b = Path(tmp, name), Path(tmp, "b.csv")
        a.write_bytes(data)
        pd.DataFrame({"x": [0.0, 1.0, 0.0, 1.0], "y": [0.0, 0.0, 1.0, 1.5]}).to_csv(b, index=False)
        code, _, err, peak = _run(["merge", str(a), str(b), "--sigma", "0.1", "-o", str(Path(tmp, "m.csv"))])
        _assert_clean(code, err, peak)


def test_the_command_on_maps_a_billion_times_apart_stays_within_its_memory_bound(tmp_path):
    """End to end in a fresh process (its own peak RSS): 500-landmark maps, b in units 1e9 times a's."""
    sc = mm.simulate.make_pair(500, 0.75, 30, rng=5)
    pd.DataFrame(sc.p, columns=["x", "y"]).to_csv(tmp_path / "a.csv", index=False)
    pd.DataFrame(sc.q * 1e9, columns=["x", "y"]).to_csv(tmp_path / "b.csv", index=False)
    code = ("import resource, sys\nfrom mapmerge.cli import main\n"
            f"status = main(['merge', 'a.csv', 'b.csv', '--sigma', '{sc.sigma!r}', '-o', 'm.csv'])\n"
            "print(status, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    status, rss_kib = map(int, run.stdout.split())
    assert status == 1 and "same units" in run.stderr and "Traceback" not in run.stderr
    assert rss_kib * 1024 < PEAK_RSS_BYTES


def test_a_map_far_from_its_origin_flat_to_rounding_is_refused_as_collinear():
    """Found by the fuzzing above: a triangle 1e-4 wide at 1e11 passed the collinearity check (relative to
    its extent) and qhull then failed on it ("initial simplex is flat"); rounding is on the scale of the
    coordinates, so the check is now relative to them too."""
    p = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]) * 1e-4 + 1e11
    q = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.2]])
    with pytest.raises(ValueError, match="P points are all collinear"):
        mm.merge_maps(p, q, 0.1)
    # A map in UTM-like coordinates (millions of metres across a kilometre) is not affected.
    utm = mm.simulate.make_pair(30, 0.75, 30, rng=1)
    assert mm.merge_maps(utm.p * 100 + 5e6, utm.q * 100, utm.sigma * 100).matched
