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
    # The one-set helper is the batch's own σ to the bit, σ̄² the edge lengths' sample variance.
    sigma, sigma_bar2 = mm.simulate.sigma_from_snr(sc.truth, 35)
    assert sigma == sc.sigma and sigma_bar2 == pytest.approx(lengths.var(ddof=1))
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
        ({"snr_db": -301.0}, r"snr_db must be a number of dB in \[-300, 300\], got -301.0"),
        ({"aspect": -1.0}, "aspect"),
        ({"aspect": 1e-4}, r"aspect must be in \[0.001, 1000\], got 0.0001"),
        ({"anisotropy": 1e4}, r"anisotropy must be in \[0, 1000\]"),
        ({"n_landmarks": 10**6, "clutter": 0.5}, r"must keep n_landmarks \* \(1 \+ clutter\) at most 1,000,000"),
        ({"n_landmarks": None}, "n_landmarks must be an integer >= 3, got None"),
        ({"overlap": "half"}, r"overlap must be in \(0, 1\], got 'half'"),
        ({"rng": 1.5}, "rng must be None, a non-negative int"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        mm.simulate.make_pair(**kwargs)
    if "rng" in kwargs:
        with pytest.raises(ValueError, match="each seed must be"):
            mm.simulate.make_pairs(10, 0.75, 20, [1, kwargs["rng"]])


def test_make_pairs_needs_a_seed():
    with pytest.raises(ValueError, match=r"seeds must hold at least one seed \(one per trial\)"):
        mm.simulate.make_pairs(10, 0.75, 20, [])


@pytest.mark.parametrize("entropy, prefix", [(0, ()), (5, (2**62 + 11,)), (2**40 + 7, (3, 0)), (2**130 + 1, (1,))])
def test_spawned_seeds_are_their_seed_sequences(entropy, prefix):
    # Trial indices across the 32-bit word boundary take the two-word path of the entropy.
    ks = np.array([0, 1, 7, 2**32 - 1, 2**32, 2**63 - 1])
    seeds = mm.simulate.SpawnedSeeds(entropy, prefix, ks)
    listed = [np.random.SeedSequence(entropy, spawn_key=(*prefix, int(k))) for k in ks]
    assert [s.spawn_key for s in seeds] == [s.spawn_key for s in listed]
    for rng, seed in zip(seeds.generators(), listed):
        assert rng.bit_generator.state == np.random.PCG64(seed).state
    a = mm.simulate.make_pairs(12, 0.75, 20, seeds, layout="interleaved", clutter=0.2, anisotropy=1.0)
    b = mm.simulate.make_pairs(12, 0.75, 20, listed, layout="interleaved", clutter=0.2, anisotropy=1.0)
    for name in ("p", "q", "ids_p", "ids_q", "truth", "sigma", "theta", "t", "cov_p", "cov_q"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("args", [(-1, (), [0]), (0, (-2,), [0]), (0, (), [-1]), (0, (), [0.5]), (0, (), [[0]]),
                                  (0, (), np.array([2**63], dtype=np.uint64))])
def test_spawned_seeds_refuse_bad_values(args):
    with pytest.raises(ValueError, match="non-negative ints"):
        mm.simulate.SpawnedSeeds(*args)


def test_interleaved_layout_puts_unshared_landmarks_among_common_ones():
    for layout, inside in (("strip", 0), ("interleaved", 5)):
        sc = mm.simulate.make_pair(100, 0.75, 40, rng=5, layout=layout, p_detect=0.9)
        assert sc.p.shape == sc.q.shape == (100, 2) and sc.n_common == 75
        common = np.intersect1d(sc.ids_p, sc.ids_q)
        only_p = np.setdiff1d(sc.ids_p, common)
        x = sc.truth[only_p, 0]
        # round(75 * 0.1 / 0.9) = 8 of p's unshared landmarks lie in the overlap.
        between = np.sum((x > sc.truth[common, 0].min()) & (x < sc.truth[common, 0].max()))
        assert between >= inside if inside else between == 0


def test_default_layout_ignores_p_detect_and_interleaved_full_detection_is_the_strip():
    a = mm.simulate.make_pair(50, 0.6, 25, rng=9)
    for kwargs in ({"p_detect": 0.5}, {"layout": "interleaved", "p_detect": 1.0}):
        b = mm.simulate.make_pair(50, 0.6, 25, rng=9, **kwargs)
        np.testing.assert_array_equal(a.p, b.p)
        np.testing.assert_array_equal(a.q, b.q)


def test_clutter_rows_belong_to_one_map():
    sc = mm.simulate.make_pair(100, 0.75, 30, rng=4, layout="interleaved", clutter=0.1)
    assert sc.p.shape == sc.q.shape == (110, 2) and sc.cov_p.shape == (110, 2, 2)
    assert sc.n_common == 75
    assert len(np.unique(sc.ids_p)) == len(np.unique(sc.ids_q)) == 110
    # p's clutter lies in p's window: within the x range of p's true landmarks' window.
    clutter_p = sc.ids_p[sc.ids_p >= 2 * 100 - 75]
    assert clutter_p.size == 10 and not np.isin(clutter_p, sc.ids_q).any()


def test_anisotropic_noise_matches_its_covariances():
    batch = mm.simulate.make_pairs(100, 0.75, 30, list(range(40)), layout="interleaved", anisotropy=3.0)
    for sc in (batch[0], batch[1]):
        # σ keeps its meaning: the mean per-coordinate variance of each map.
        for cov in (sc.cov_p, sc.cov_q):
            assert np.mean(np.trace(cov, axis1=1, axis2=2)) / 2 == pytest.approx(sc.sigma**2)
    rows = np.arange(len(batch))[:, None]
    rp = batch.p - batch.truth[rows, batch.ids_p]
    rq = batch.q - (mm.alignment.rotate(batch.theta, batch.truth[rows, batch.ids_q]) + batch.t[:, None])
    for r, cov in ((rp, batch.cov_p), (rq, batch.cov_q)):
        # Whitened residuals are χ²₂: mean 2 over 8,000 landmarks.
        d2 = np.einsum("...i,...ij,...j->...", r, np.linalg.inv(cov), r)
        assert d2.mean() == pytest.approx(2.0, rel=0.05)
        eig = np.linalg.eigvalsh(cov)
        assert eig[..., 1].max() / eig[..., 0].min() > 9  # 4x the deviation at the window's edge
    iso = mm.simulate.make_pair(100, 0.75, 30, rng=1)
    np.testing.assert_allclose(iso.cov_p, np.broadcast_to(iso.sigma**2 * np.eye(2), (100, 2, 2)))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"layout": "ring"}, "layout"),
        ({"p_detect": 0.0}, "p_detect"),
        ({"p_detect": 1.2}, "p_detect"),
        ({"clutter": -0.1}, "clutter"),
        ({"clutter": float("inf")}, "clutter"),
        ({"anisotropy": -1.0}, "anisotropy"),
    ],
)
def test_bad_layout_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        mm.simulate.make_pair(**kwargs)
