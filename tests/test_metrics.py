import numpy as np
import pytest

import mapmerge as mm
from mapmerge import metrics


def test_roc_matches_brute_force(rng):
    y = rng.random(300) < 0.3
    s = np.round(rng.normal(size=300) + 1.5 * y, 1)  # rounding creates ties
    fpr, tpr, thr = metrics.roc_curve(y, s)
    assert thr[0] == np.inf and np.all(np.diff(thr) < 0)
    for f, t, th in zip(fpr, tpr, thr):
        dec = s >= th
        assert t == pytest.approx(np.mean(dec[y]))
        assert f == pytest.approx(np.mean(dec[~y]))
    assert fpr[-1] == tpr[-1] == 1.0
    # AUC equals the Mann-Whitney probability (ties count one half).
    pos, neg = s[y][:, None], s[~y][None, :]
    assert metrics.auc(fpr, tpr) == pytest.approx(np.mean((pos > neg) + 0.5 * (pos == neg)))


def test_roc_rejects_bad_input():
    with pytest.raises(ValueError, match="same length"):
        metrics.roc_curve([True, False], [0.1])
    with pytest.raises(ValueError, match="NaN"):
        metrics.roc_curve([True, False], [np.nan, 0.1])
    with pytest.raises(ValueError, match=r"y_true must hold booleans or 0/1 labels, got values \[2, 3\]"):
        metrics.roc_curve([2, 3], [0.1, 0.2])
    with pytest.raises(ValueError, match="fpr and tpr must be 1-D and of the same length"):
        metrics.auc([0, 1], [0])
    with pytest.raises(ValueError, match=r"fpr must be non-decreasing \(the points in roc_curve's order\)"):
        metrics.auc([0.5, 0.0, 1.0], [0.5, 0.0, 1.0])
    # 0/1 labels are booleans
    assert all(np.array_equal(a, b) for a, b in zip(metrics.roc_curve([1, 0, 1], [0.3, 0.2, 0.1]),
                                                    metrics.roc_curve([True, False, True], [0.3, 0.2, 0.1])))


def test_map_errors_names_a_result_that_is_not_a_merge():
    sc = mm.simulate.make_pair(20, 0.75, 30, rng=0)
    with pytest.raises(ValueError, match="result must be the MergeResult of merge_maps, got str"):
        metrics.map_errors(sc, "x")


def test_oracle_tau_gives_zero_fp(rng):
    y = rng.random(200) < 0.4
    s = rng.normal(size=200) + 2 * y
    lt = metrics.oracle_log_tau(y, s)
    c = metrics.detection_counts(y, s >= lt, n_common=int(y.sum()) + 3)
    assert c["fp"] == 0 and c["tp"] > 0 and c["unpaired"] == 3
    assert c["tp"] + c["md"] == y.sum() and c["tp"] + c["fp"] + c["md"] + c["tn"] == 200
    # Any lower threshold admits the best false pair.
    assert metrics.detection_counts(y, s >= np.nextafter(lt, -np.inf), 0)["fp"] == 1
    assert metrics.oracle_log_tau(np.ones(3, bool), [1.0, 2, 3]) == -np.inf


def test_labels_and_common_triangles():
    sc = mm.simulate.make_pair(40, 0.75, 60, rng=4)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="paper")
    vp, vq = res.tri_p.vertices, res.tri_q.vertices
    common = metrics.common_triangles(sc.ids_p, sc.ids_q, vp, vq)
    for i, j in common:
        assert set(sc.ids_p[vp[i]]) == set(sc.ids_q[vq[j]])
    is_true, consistent = metrics.triangle_labels(sc.ids_p, sc.ids_q, vp, vq, res.triangle_pairs)
    assert np.all(is_true[consistent])
    # At 60 dB every common triangle is found with its true partner.
    assert is_true.sum() == len(common) and consistent.sum() == len(common)


def _brute_force_association(score):
    """Best one-to-one partial pairing by enumeration (pairs with score <= 0 never help)."""
    from itertools import permutations

    n_p, n_q = score.shape
    best, best_pairs = 0.0, []
    cols = list(range(n_q)) + [None] * n_p
    for perm in set(permutations(cols, n_p)):
        total = sum(score[i, j] for i, j in enumerate(perm) if j is not None and score[i, j] > 0)
        if total > best + 1e-12:
            best = total
            best_pairs = sorted((i, j) for i, j in enumerate(perm) if j is not None and score[i, j] > 0)
    return best, best_pairs


def test_oracle_association_is_the_best_pairing_by_enumeration(rng):
    for _ in range(40):
        n_p, n_q = int(rng.integers(2, 5)), int(rng.integers(2, 5))
        P = rng.uniform(0, 1.5, (n_p, 2))
        Q = rng.uniform(0, 1.5, (n_q, 2))
        cov_p = np.einsum("n,ij->nij", rng.uniform(0.01, 0.1, n_p), np.eye(2))
        cov_q = np.einsum("n,ij->nij", rng.uniform(0.01, 0.1, n_q), np.eye(2))
        theta, t = 0.0, np.zeros(2)
        pairs = metrics.oracle_association(P, Q, theta, t, cov_p, cov_q, density_q=1.0, p_shared=0.5)
        C = cov_p[:, None] + cov_q[None]
        e = P[:, None] - Q[None]
        d2 = np.einsum("abi,abij,abj->ab", e, np.linalg.inv(C), e)
        score = -0.5 * d2 - np.log(2 * np.pi * np.sqrt(np.linalg.det(C)))  # log λ = 0, log odds = 0
        _, expected = _brute_force_association(score)
        assert [tuple(p) for p in pairs.tolist()] == expected


def test_oracle_association_on_a_synthetic_pair():
    sc = mm.simulate.make_pair(100, 0.75, 40, rng=3)
    cov = sc.sigma**2 * np.eye(2)
    pairs = metrics.oracle_association(sc.p, sc.q, sc.theta, sc.t, np.broadcast_to(cov, (100, 2, 2)),
                                       np.broadcast_to(cov, (100, 2, 2)), density_q=1.0, p_shared=0.75)
    correct = np.sum(sc.ids_p[pairs[:, 0]] == sc.ids_q[pairs[:, 1]])
    assert correct == sc.n_common and len(pairs) == correct


def test_oracle_pairs_and_transform_found_on_a_batch():
    batch = mm.simulate.make_pairs(100, 0.75, 40, [1, 2, 3], layout="interleaved", clutter=0.1)
    oracle = metrics.oracle_pairs_batch(batch)
    # At 40 dB the oracle pairs every common landmark and nothing else.
    np.testing.assert_array_equal(oracle["oracle_correct_pairs"], [75, 75, 75])
    np.testing.assert_array_equal(oracle["oracle_wrong_pairs"], [0, 0, 0])
    sc = batch[0]
    res = mm.merge_maps(sc.p, sc.q, sc.sigma)
    assert metrics.map_errors(sc, res)["transform_found"]
    # The same correspondences with q turned by 2 degrees about its centroid: the transform is wrong.
    centre = sc.q.mean(axis=0)
    turned = mm.alignment.rotate(np.radians(2.0), sc.q - centre) + centre
    off = mm.merge_maps(sc.p, turned, sc.sigma)
    assert off.matched and not metrics.map_errors(sc, off)["transform_found"]


def test_transform_oracle_knows_the_transform_but_not_the_prior():
    high = metrics.oracle_pairs_batch(mm.simulate.make_pairs(100, 0.75, 40, [1, 2, 3], layout="interleaved"))
    np.testing.assert_array_equal(high["transform_oracle_correct_pairs"], [75, 75, 75])
    np.testing.assert_array_equal(high["transform_oracle_wrong_pairs"], [0, 0, 0])
    # At 10 dB in the strip layout every q landmark among p's is shared (π = 1): the oracle that
    # knows it pairs more common landmarks than one that estimates π from the maps, but not many
    # more, because the estimate corrects for the association's own misses (without that
    # correction these pairs gave 0.955x).
    low = metrics.oracle_pairs_batch(mm.simulate.make_pairs(100, 0.75, 10, range(50, 62)))
    assert low["transform_oracle_correct_pairs"].sum() < low["oracle_correct_pairs"].sum()
    assert low["transform_oracle_correct_pairs"].sum() > 0.98 * low["oracle_correct_pairs"].sum()
    sc = mm.simulate.make_pair(100, 0.75, 10, rng=50)
    pairs = metrics.transform_oracle_association(sc.p, sc.q, sc.theta, sc.t, sc.sigma)
    ok = sc.ids_p[pairs[:, 0]] == sc.ids_q[pairs[:, 1]]
    assert (ok.sum(), (~ok).sum()) == (low["transform_oracle_correct_pairs"][0], low["transform_oracle_wrong_pairs"][0])


def test_correspondence_oracle_fits_every_true_pair_with_the_cramer_rao_spread():
    batch = mm.simulate.make_pairs(100, 0.75, 10, range(900, 1100), layout="interleaved")
    z = []
    for sc in (batch[k] for k in range(len(batch))):
        fit = metrics.correspondence_oracle_transform(sc)
        # The closed form over the landmarks paired by id (in p's order here: the same up to rounding).
        where = {i: k for k, i in enumerate(sc.ids_q)}
        ip = [k for k, i in enumerate(sc.ids_p) if i in where]
        same = mm.align(sc.p[ip], sc.q[[where[sc.ids_p[k]] for k in ip]], sc.sigma)
        assert fit.theta == pytest.approx(same.theta, abs=1e-12) and np.allclose(fit.t, same.t, rtol=0, atol=1e-12)
        assert len(ip) == sc.n_common
        z.append(mm.alignment.wrap_angle(fit.theta - sc.theta) / np.sqrt(fit.cov[0, 0]))
    # Efficient: its rotation error is spread as the Cramér-Rao bound with the correspondences known says.
    assert 0.85 < np.std(z) < 1.15 and abs(np.mean(z)) < 0.2
    unrelated = mm.simulate.make_pair(20, 0.75, 10, rng=1, unrelated=True)
    with pytest.raises(ValueError, match="scenario must share at least 2 landmarks"):
        metrics.correspondence_oracle_transform(unrelated)
