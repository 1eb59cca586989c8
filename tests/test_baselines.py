"""Outside baselines (mapmerge.baselines): Groth's voting and astroalign."""

import threading

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import metrics


def test_groth_baseline_recovers_the_transform():
    sc = mm.simulate.make_pair(100, 0.75, 40, rng=1)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="groth")
    err = metrics.map_errors(sc, res)
    assert err["success"] and err["wrong_pairs"] == 0 and err["correct_pairs"] > 50


def test_groth_reports_the_glrt_of_each_pair_it_votes_with():
    sc = mm.simulate.make_pair(60, 0.75, 20, rng=3)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="groth")
    log_lr = mm.glrt(res.tri_p.coords, res.tri_q.coords, sc.sigma)
    assert len(res.triangle_pairs) > 100
    np.testing.assert_array_equal(res.triangle_log_lr, log_lr[res.triangle_pairs[:, 0], res.triangle_pairs[:, 1]])


def test_astroalign_baseline():
    pytest.importorskip("astroalign")
    sc = mm.simulate.make_pair(50, 0.75, 40, rng=1)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="astroalign")
    assert metrics.map_errors(sc, res)["rot_err_deg"] < 0.5
    # Three points cannot be matched by astroalign: an honest "no match".
    tiny = mm.merge_maps(sc.p[:3], sc.q[:3] + 100, sc.sigma, method="astroalign")
    assert not tiny.matched


def test_astroalign_baseline_is_reproducible():
    pytest.importorskip("astroalign")
    default_rng = np.random.default_rng
    # At 20 dB its RANSAC's random draws decide the answer; they are seeded
    # from the maps, so the same maps give the same merge, and numpy's
    # default_rng is left as it was.
    sc = mm.simulate.make_pair(60, 0.75, 20, rng=0)
    a, b = (mm.merge_maps(sc.p, sc.q, sc.sigma, method="astroalign") for _ in range(2))
    assert np.array_equal(a.pairs, b.pairs) and np.array_equal(a.t, b.t, equal_nan=True)
    # The caller's generator drives the RANSAC instead: the same seed, the same answer.
    sc = mm.simulate.make_pair(60, 0.75, 30, rng=0)
    c, d = (mm.merge_maps(sc.p, sc.q, sc.sigma, method="astroalign", rng=7) for _ in range(2))
    assert np.array_equal(c.pairs, d.pairs) and len(c.pairs) > 10
    assert np.random.default_rng is default_rng


def test_astroalign_calls_from_two_threads_each_draw_from_their_own_generator(monkeypatch):
    astroalign = pytest.importorskip("astroalign")
    default_rng = np.random.default_rng
    from mapmerge.baselines.astroalign import astroalign_pairs

    sc = mm.simulate.make_pair(30, 0.75, 30, rng=0)
    gens = {"first": np.random.default_rng(1), "second": np.random.default_rng(2)}
    first_inside, second_inside, seen = threading.Event(), threading.Event(), {}
    real = astroalign.find_transform

    def find_transform(*args, **kwargs):
        # The first call waits inside for the second (0.5 s at most): it can get there only if the
        # two calls' replacements of numpy's default_rng overlap.
        name = threading.current_thread().name
        if name == "first":
            first_inside.set()
            second_inside.wait(0.5)
        else:
            second_inside.set()
        seen[name] = np.random.default_rng()
        # A thread outside the call draws fresh entropy, as numpy does.
        outside = []
        helper = threading.Thread(target=lambda: outside.append(np.random.default_rng()))
        helper.start()
        helper.join()
        seen[name + " outside"] = outside[0]
        return real(*args, **kwargs)

    monkeypatch.setattr(astroalign, "find_transform", find_transform)
    threads = {name: threading.Thread(target=astroalign_pairs, args=(sc.p, sc.q, sc.sigma, gen), name=name)
               for name, gen in gens.items()}
    threads["first"].start()
    assert first_inside.wait(10)
    threads["second"].start()
    for thread in threads.values():
        thread.join()
    assert seen["first"] is gens["first"] and seen["second"] is gens["second"]
    assert not {id(seen["first outside"]), id(seen["second outside"])} & {id(g) for g in gens.values()}
    assert np.random.default_rng is default_rng


def test_groth_on_a_batch_equals_each_map_pair_alone():
    batch = mm.simulate.make_pairs(20, 0.75, 25, list(range(12)))
    merged = mm.merge_batch(batch.p, batch.q, batch.sigma, method="groth")
    found = 0
    for b in range(12):
        alone = mm.merge_maps(batch.p[b], batch.q[b], batch.sigma[b], method="groth")
        res = merged.result(b)
        np.testing.assert_array_equal(res.pairs, alone.pairs)
        np.testing.assert_array_equal(res.triangle_pairs, alone.triangle_pairs)
        np.testing.assert_array_equal(res.declared, alone.declared)
        np.testing.assert_array_equal(res.triangle_log_lr, alone.triangle_log_lr)
        assert res.n_conflicts == alone.n_conflicts and res.matched == alone.matched
        found += res.matched
    assert found >= 6


def test_groth_on_a_large_map_runs_in_slices_and_refuses_beyond_its_pair_limit(monkeypatch):
    from mapmerge.baselines import groth

    sc = mm.simulate.make_pair(300, 0.75, 30, rng=2)  # about 600 x 600 triangles: the sliced path
    sliced = mm.merge_maps(sc.p, sc.q, sc.sigma, method="groth")
    monkeypatch.setattr(groth, "BLOCK_PAIRS", 10**7)  # the whole map pair in one block
    whole = mm.merge_maps(sc.p, sc.q, sc.sigma, method="groth")
    for a, b in ((sliced.triangle_pairs, whole.triangle_pairs), (sliced.triangle_log_lr, whole.triangle_log_lr),
                 (sliced.pairs, whole.pairs), (sliced.t, whole.t)):
        np.testing.assert_array_equal(a, b)
    assert sliced.matched and len(sliced.triangle_pairs) > 10_000
    # Beyond the limit of passing pairs: one line naming the method and the way out, not an exhausted memory.
    monkeypatch.setattr(groth, "GROTH_MAX_PAIRS", 5_000)
    with pytest.raises(ValueError, match=r"method 'groth': over 5,000 triangle pairs .* use method='consensus'"):
        mm.merge_maps(sc.p, sc.q, sc.sigma, method="groth")
