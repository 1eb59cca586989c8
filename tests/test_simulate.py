import numpy as np
import pytest

import mapmerge as mm
from mapmerge.triangles import delaunay_edges


@pytest.mark.parametrize("n, overlap, common", [(100, 0.75, 75), (10, 0.5, 5), (20, 1.0, 20)])
def test_counts_and_ids(n, overlap, common):
    sc = mm.simulate.make_pair(n, overlap, 30, rng=3)
    assert sc.p.shape == sc.q.shape == (n, 2)
    assert sc.n_common == common
    assert len(np.unique(sc.ids_p)) == len(np.unique(sc.ids_q)) == n
    assert sc.truth.shape == (2 * n - common, 2)


def test_snr_definition_and_frames():
    sc = mm.simulate.make_pair(100, 0.75, 35, rng=11)
    edges = delaunay_edges(sc.truth)
    lengths = np.linalg.norm(sc.truth[edges[:, 0]] - sc.truth[edges[:, 1]], axis=1)
    assert 10 * np.log10(lengths.var(ddof=1) / (2 * sc.sigma**2)) == pytest.approx(35)
    # Residuals in each frame are the noise: about σ per coordinate.
    rp = sc.p - sc.truth[sc.ids_p]
    rq = sc.q - (sc.truth[sc.ids_q] @ mm.rotation(sc.theta).T + sc.t)
    assert np.std(np.r_[rp, rq]) == pytest.approx(sc.sigma, rel=0.15)


def test_common_landmarks_in_overlap_strip():
    sc = mm.simulate.make_pair(100, 0.5, 40, rng=5)
    common = np.intersect1d(sc.ids_p, sc.ids_q)
    only_p = np.setdiff1d(sc.ids_p, common)
    assert sc.truth[common, 0].min() > sc.truth[only_p, 0].max()


def test_reproducible_and_seed_sensitive():
    a = mm.simulate.make_pair(30, 0.75, 30, rng=np.random.SeedSequence(1))
    b = mm.simulate.make_pair(30, 0.75, 30, rng=np.random.SeedSequence(1))
    c = mm.simulate.make_pair(30, 0.75, 30, rng=2)
    np.testing.assert_array_equal(a.q, b.q)
    assert not np.array_equal(a.q, c.q)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_landmarks": 2}, "n_landmarks"),
        ({"n_landmarks": 10.5}, "n_landmarks"),
        ({"overlap": 0.0}, "overlap"),
        ({"overlap": 1.5}, "overlap"),
        ({"n_landmarks": 4, "overlap": 0.5}, "at least 3 common"),
        ({"snr_db": float("nan")}, "snr_db"),
        ({"aspect": -1.0}, "aspect"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        mm.simulate.make_pair(**kwargs)
