"""Landmark association under a fitted transform (mapmerge.association)."""

import numpy as np

import mapmerge as mm
from mapmerge.association import associate, declared_triangles, own_covariances, posterior_association
from mapmerge.metrics import KnownTransform


def _true_pairs(sc):
    """The (p row, q row) pairs of the landmarks both maps hold."""
    _, ip, iq = np.intersect1d(sc.ids_p, sc.ids_q, return_indices=True)
    return np.stack([ip, iq], axis=1)[np.argsort(ip)]


def test_associate_at_the_true_transform_pairs_the_common_landmarks():
    sc = mm.simulate.make_pair(100, 0.75, 30.0, rng=11)
    pairs, contested = associate(sc.p, sc.q, KnownTransform(sc.theta, sc.t), sc.sigma)
    truth = {tuple(r) for r in _true_pairs(sc)}
    found = {tuple(r) for r in pairs}
    assert len(found & truth) >= 0.95 * len(truth) and len(found - truth) <= 1
    assert contested.shape == (len(pairs),) and contested.dtype == bool
    assert np.all(np.diff(pairs[:, 0]) > 0)  # one-to-one, sorted by p
    assert associate(sc.p, sc.q, KnownTransform(sc.theta, sc.t), sc.sigma, with_margin=False)[1] is None


def test_declared_triangles_are_those_with_three_associated_vertices():
    rng = np.random.default_rng(5)
    P = rng.uniform(0, 10, (30, 2))
    perm = rng.permutation(30)
    Q = mm.alignment.rotate(0.3, P[perm][None])[0] + [2.0, -1.0]  # q row k is p row perm[k]
    vp, vq = mm.triangulate(P).vertices, mm.triangulate(Q).vertices
    inverse = np.argsort(perm)
    pairs = np.stack([np.arange(30), inverse], axis=1)
    tri_pairs, log_lr = declared_triangles(vp, vq, pairs, P, Q, 0.1)
    # Noise-free congruent maps: every p triangle has its q counterpart, with log Λ = 0.
    assert len(tri_pairs) == len(vp) and np.allclose(log_lr, 0.0, atol=1e-9)
    np.testing.assert_array_equal(np.sort(inverse[vp[tri_pairs[:, 0]]], axis=1), np.sort(vq[tri_pairs[:, 1]], axis=1))
    # Without landmark 0 associated, exactly the triangles on it drop out.
    fewer, _ = declared_triangles(vp, vq, pairs[1:], P, Q, 0.1)
    np.testing.assert_array_equal(np.sort(fewer[:, 0]), np.flatnonzero(~np.any(vp == 0, axis=1)))


def test_own_covariances_default_to_sigma_squared():
    cov = own_covariances(None, 4, 0.5)
    assert cov.shape == (4, 2, 2) and np.array_equal(cov[2], 0.25 * np.eye(2))
    given = np.ones((3, 2, 2))
    assert own_covariances(given, 3, 0.5) is given


def test_posterior_association_margins_are_optional():
    # Skipping the margins (one assignment per contested pair) must not change the pairs.
    sc = mm.simulate.make_pair(100, 0.75, 5.0, rng=3)
    x = mm.alignment.rotate(-sc.theta, sc.q - sc.t)
    cov = np.broadcast_to(sc.sigma**2 * np.eye(2), (100, 2, 2))
    pairs, margin = posterior_association(sc.p, x, cov, cov, np.log(4.0) - np.log(sc.density))
    fast, none = posterior_association(sc.p, x, cov, cov, np.log(4.0) - np.log(sc.density), with_margin=False)
    np.testing.assert_array_equal(fast, pairs)
    assert none is None and len(margin) == len(pairs) and np.any(np.isfinite(margin))


def test_associate_batch_is_each_map_pair_associated_alone():
    # A batch numbers the map pairs' landmarks apart: no landmark may compete with another pair's,
    # and π is estimated per pair, so the batch must give exactly the pairs' own associations.
    scs = [mm.simulate.make_pair(30, 0.75, snr, rng=seed) for seed, snr in enumerate((10.0, 20.0, 30.0))]
    cov = np.diag([1e-4, 1e-2, 1e-2])  # an imperfect fit, so the gate widens with distance
    trial, pairs, contested = mm.association.associate_batch(
        np.stack([sc.p for sc in scs]), np.stack([sc.q for sc in scs]), np.array([sc.theta for sc in scs]),
        np.stack([sc.t for sc in scs]), np.stack([cov] * 3), np.array([sc.sigma for sc in scs]))
    for b, sc in enumerate(scs):
        alone, alone_contested = associate(sc.p, sc.q, KnownTransform(sc.theta, sc.t, cov), sc.sigma)
        np.testing.assert_array_equal(pairs[trial == b], alone)
        np.testing.assert_array_equal(contested[trial == b], alone_contested)


def test_two_by_two_components_are_solved_as_the_assignment_solver_does(monkeypatch, rng):
    """The vectorised 2 x 2 components of ``_assign`` give the solver's pairs and margins, bit for bit."""
    from mapmerge import association

    real, handled = association._two_by_two, []

    def counting(*args):
        out = real(*args)
        handled.append(int(out[0].sum()))
        return out

    def nothing(i, j, score, comp, with_margin):
        n = int(comp.max()) + 1 if comp.size else 0
        return np.zeros(n, dtype=bool), np.empty((0, 2), dtype=np.intp), np.empty(0)

    for k in range(30):
        n_p, n_q = rng.integers(5, 60, 2)
        m = int(rng.integers(1, 3 * min(n_p, n_q)))
        i, j = rng.integers(0, n_p, m), rng.integers(0, n_q, m)
        first = np.unique(i * n_q + j, return_index=True)[1]
        i, j = i[first], j[first]
        score = rng.uniform(-1, 3, len(i))
        if k % 2:  # many exact ties, which the solver decides
            score = rng.choice([1.0, 2.0, -1.0], size=len(i)) * rng.integers(1, 3, len(i))
        for with_margin in (True, False):
            monkeypatch.setattr(association, "_two_by_two", counting)
            fast = association._assign(i, j, score, n_p, n_q, with_margin)
            monkeypatch.setattr(association, "_two_by_two", nothing)
            slow = association._assign(i, j, score, n_p, n_q, with_margin)
            np.testing.assert_array_equal(fast[0], slow[0])
            if with_margin:
                np.testing.assert_array_equal(fast[1], slow[1])
    assert sum(handled) > 50  # the fast path did run
