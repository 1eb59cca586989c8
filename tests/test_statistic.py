"""Theorem 1 against brute force, the χ² law under H1, glrt's matrix form, the order-robust statistic."""

import numpy as np
import pytest
from scipy import optimize, stats

import mapmerge as mm
from mapmerge import metrics
from mapmerge.alignment import paired_transforms
from mapmerge.triangles import ccw_order, groth_order


def _profile(theta, P, Q):
    """min over µ, t of eq. (5) at fixed θ, by generic linear least squares."""
    n = P.shape[0]
    R = mm.rotation(theta)
    # Unknowns x = [µ (2n), t (2)]; residuals [P - µ ; Q - R µ - t].
    A = np.zeros((4 * n, 2 * n + 2))
    A[: 2 * n, : 2 * n] = np.eye(2 * n)
    A[2 * n :, : 2 * n] = np.kron(np.eye(n), R)
    A[2 * n :, 2 * n :] = np.tile(np.eye(2), (n, 1))
    b = np.concatenate([P.ravel(), Q.ravel()])
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ x
    return float(r @ r), x[: 2 * n].reshape(n, 2), x[2 * n :]


def _d_profile(theta, P, Q):
    """dJ/dθ by the envelope theorem at the least-squares µ, t."""
    _, mu, t = _profile(theta, P, Q)
    c, s = np.cos(theta), np.sin(theta)
    dR = np.array([[-s, -c], [c, -s]])
    resid = Q - mu @ mm.rotation(theta).T - t
    return float(-2 * np.sum(resid * (mu @ dR.T)))


def brute_force(P, Q):
    grid = np.linspace(-np.pi, np.pi, 2881)
    values = np.array([_profile(th, P, Q)[0] for th in grid])
    k = int(np.argmin(values))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    dlo, dhi = _d_profile(lo, P, Q), _d_profile(hi, P, Q)
    if dlo < 0 < dhi:
        theta = optimize.brentq(_d_profile, lo, hi, args=(P, Q), xtol=1e-15, rtol=1e-15)
    else:  # optimum exactly on a grid point (e.g. θ = ±π)
        theta = grid[k]
    J, mu, t = _profile(theta, P, Q)
    return J, float(mm.wrap_angle(theta)), t, mu


def _check_against_brute(P, Q):
    al = mm.align(P, Q, sigma=1.0)
    J, theta, t, mu = brute_force(P, Q)
    # The brute force works in raw coordinates, so its rounding floor scales
    # with their magnitude, not with the (possibly tiny) centred spread.
    scale = np.sum(P**2) + np.sum(Q**2)
    assert al.cost == pytest.approx(J, rel=1e-8, abs=1e-12 * scale)
    assert abs(float(mm.wrap_angle(al.theta - theta))) < 1e-8
    np.testing.assert_allclose(al.t, t, rtol=1e-8, atol=1e-8 * np.sqrt(scale))
    np.testing.assert_allclose(al.mu, mu, rtol=1e-8, atol=1e-8 * np.sqrt(scale))


@pytest.mark.parametrize("n", [3, 3, 3, 5, 12])
def test_closed_form_matches_brute_force_random(rng, n):
    for _ in range(4):
        P = rng.normal(size=(n, 2)) * rng.uniform(0.5, 20)
        theta = rng.uniform(-np.pi, np.pi)
        Q = P @ mm.rotation(theta).T + rng.normal(size=2) * 10 + rng.normal(size=(n, 2)) * rng.uniform(0.01, 2)
        _check_against_brute(P, Q)


@pytest.mark.parametrize("theta", [0.0, np.pi, np.pi / 2, -np.pi / 2])
def test_beta_zero_and_quarter_turns(rng, theta):
    P = rng.normal(size=(3, 2))
    Q = P @ mm.rotation(theta).T + np.array([3.0, -1.0])
    al = mm.align(P, Q)
    assert abs(float(mm.wrap_angle(al.theta - theta))) < 1e-12
    assert al.cost < 1e-20
    _check_against_brute(P, Q + rng.normal(size=(3, 2)) * 0.05)


def test_paper_theta_formula_is_wrong_only_at_beta_zero_pi(rng):
    """sgn(β)[acos(α/r) - π] gives 0 where the optimum is π; atan2 gives π."""
    P = rng.normal(size=(3, 2))
    Q = -P  # θ = π exactly: β = 0, α > 0
    pc, qc = P - P.mean(0), Q - Q.mean(0)
    alpha = -np.sum(qc * pc)
    beta = -np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0])
    paper = np.sign(beta) * (np.arccos(alpha / np.hypot(alpha, beta)) - np.pi)
    assert paper == 0.0
    assert mm.align(P, Q).theta == pytest.approx(np.pi)
    # Elsewhere both forms agree.
    Q2 = P @ mm.rotation(1.0).T
    pc, qc = P - P.mean(0), Q2 - Q2.mean(0)
    alpha = -np.sum(qc * pc)
    beta = -np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0])
    paper = np.sign(beta) * (np.arccos(alpha / np.hypot(alpha, beta)) - np.pi)
    assert float(mm.wrap_angle(paper)) == pytest.approx(mm.align(P, Q2).theta)


def test_near_degenerate_triangles(rng):
    # Nearly collinear, nearly coincident and badly scaled triangles.
    cases = [
        np.array([[0.0, 0.0], [1.0, 1e-6], [2.0, -1e-6]]),
        np.array([[0.0, 0.0], [1e-4, 0.0], [0.0, 1e-4]]),
        np.array([[0.0, 0.0], [1000.0, 0.0], [500.0, 0.01]]),
    ]
    for P in cases:
        theta = rng.uniform(-np.pi, np.pi)
        # Offsets in proportion to the triangle: the brute force in raw
        # coordinates cannot resolve θ of a 1e-4 triangle sitting at 100.
        Q = P @ mm.rotation(theta).T + np.ptp(P) * (5.0 + rng.normal(size=(3, 2)) * 1e-3)
        _check_against_brute(P, Q)


def test_mu_in_p_frame_is_midpoint():
    P = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]])
    Q = P @ mm.rotation(0.3).T + [1.0, 2.0]
    al = mm.align(P, Q)
    np.testing.assert_allclose(al.mu, P, atol=1e-12)
    assert al.dof == 3


def test_glrt_matrix_equals_pairwise_fits(rng):
    cp = rng.normal(size=(7, 3, 2)) * 3
    cq = rng.normal(size=(5, 3, 2)) * 3
    cq[2] = cp[4] @ mm.rotation(2.0).T + 1.0
    sigma = 0.7
    L = mm.glrt(cp, cq, sigma)
    assert L.shape == (7, 5)
    ii, jj = np.meshgrid(np.arange(7), np.arange(5), indexing="ij")
    _, _, cost = paired_transforms(cp[ii.ravel()], cq[jj.ravel()])
    np.testing.assert_allclose(L.ravel(), -cost / (2 * sigma**2), rtol=1e-9, atol=1e-9)
    assert np.all(L <= 0)
    assert L[4, 2] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("cyclic", [False, True])
def test_cost_of_listed_pairs_is_bitwise_the_cost_of_every_pair(rng, cyclic):
    """``min_cost(..., pairs=)`` (each triangle centred once, blocks of pairs) gives the bits of the
    full matrix, and of each pair's triangles alone."""
    from mapmerge.statistic import BLOCK_PAIRS, min_cost

    cp = rng.normal(size=(60, 3, 2)) * rng.uniform(0.01, 100, (60, 1, 1)) + rng.normal(0, 1e3, (60, 1, 2))
    cq = rng.normal(size=(40, 3, 2)) * rng.uniform(0.01, 100, (40, 1, 1)) + rng.normal(0, 1e3, (40, 1, 2))
    i, j = rng.integers(0, 60, BLOCK_PAIRS + 999), rng.integers(0, 40, BLOCK_PAIRS + 999)  # two blocks
    cost, shift = min_cost(cp, cq, cyclic, pairs=(i, j))
    full_cost, full_shift = min_cost(cp, cq, cyclic)
    rows = np.arange(len(i))
    rows_cost, rows_shift = min_cost(cp[i], cq[j], cyclic, pairs=(rows, rows))
    assert cost.tobytes() == full_cost[i, j].tobytes() == rows_cost.tobytes()
    assert shift.tobytes() == full_shift[i, j].tobytes() == rows_shift.tobytes()
    none = min_cost(cp, cq, cyclic, pairs=(i[:0], j[:0]))
    assert none[0].shape == none[1].shape == (0,)


@pytest.mark.parametrize("n", [3, 6])
def test_minus_two_log_lr_is_chi2_under_h1(n):
    """-2 log Λ ~ χ²(2n - 3) under H1: Monte Carlo + KS test, fixed seed."""
    rng = np.random.default_rng(7)
    m, sigma = 4000, 0.05
    mu = rng.uniform(0, 10, size=(m, n, 2))
    theta = rng.uniform(-np.pi, np.pi, size=m)
    c, s = np.cos(theta), np.sin(theta)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    P = mu + rng.normal(scale=sigma, size=mu.shape)
    Q = np.einsum("mij,mvj->mvi", R, mu) + rng.normal(size=(m, 1, 2)) * 5 + rng.normal(scale=sigma, size=mu.shape)
    _, _, cost = paired_transforms(P, Q)
    stat = cost / sigma**2
    ks = stats.kstest(stat, stats.chi2(2 * n - 3).cdf)
    print(f"n={n}: KS D={ks.statistic:.4f} p={ks.pvalue:.3f}, mean={stat.mean():.3f} (expect {2*n-3})")
    assert ks.pvalue > 0.01
    # A wrong dof must be rejected: the test has power.
    assert stats.kstest(stat, stats.chi2(2 * n - 2).cdf).pvalue < 1e-6


def test_glrt_and_align_validate():
    with pytest.raises(ValueError, match="coords_p"):
        mm.glrt(np.zeros((4, 2, 2)), np.zeros((4, 3, 2)), 1.0)
    with pytest.raises(ValueError, match="coords_q"):
        mm.glrt(np.zeros((4, 3, 2)), np.full((4, 3, 2), np.nan), 1.0)
    with pytest.raises(ValueError, match="sigma"):
        mm.glrt(np.zeros((4, 3, 2)), np.zeros((4, 3, 2)), 0.0)
    with pytest.raises(ValueError, match="same shape"):
        mm.align(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="P needs at least 2"):
        mm.align(np.zeros((1, 2)), np.zeros((1, 2)))


def test_covariances_match_monte_carlo():
    """Predicted cov of θ*, t*, µ* within 10 % of the empirical one."""
    rng = np.random.default_rng(3)
    K, m, sigma, theta = 8, 20000, 0.02, 0.7
    mu = rng.uniform(-3, 5, size=(K, 2))
    t = np.array([2.0, -1.0])
    R = mm.rotation(theta)
    P = mu + rng.normal(scale=sigma, size=(m, K, 2))
    Q = mu @ R.T + t + rng.normal(scale=sigma, size=(m, K, 2))
    th, tt, _ = paired_transforms(P, Q)
    eta = np.column_stack([th, tt])
    pred = mm.align(mu, mu @ R.T + t, sigma)  # evaluated at the truth
    emp = np.cov(eta.T)
    np.testing.assert_allclose(np.diag(emp), np.diag(pred.cov), rtol=0.1)
    assert np.linalg.norm(emp - pred.cov) < 0.1 * np.linalg.norm(pred.cov)
    c, s = np.cos(th), np.sin(th)
    # µ*_v = ½ (p_v + Rᵀ (q_v - t)) per draw.
    d = Q - tt[:, None, :]
    mu_hat = 0.5 * (P + np.stack([c[:, None] * d[..., 0] + s[:, None] * d[..., 1],
                                  -s[:, None] * d[..., 0] + c[:, None] * d[..., 1]], -1))
    for v in range(K):
        emp_v = np.cov(mu_hat[:, v].T)
        assert np.linalg.norm(emp_v - pred.mu_cov[v]) < 0.1 * np.linalg.norm(pred.mu_cov[v])


def _counts(sc, res):
    vp, vq = res.tri_p.vertices, res.tri_q.vertices
    is_true, _ = metrics.triangle_labels(sc.ids_p, sc.ids_q, vp, vq, res.triangle_pairs)
    n_common = len(metrics.common_triangles(sc.ids_p, sc.ids_q, vp, vq))
    return metrics.detection_counts(is_true, res.declared, n_common)


def test_groth_flip_is_a_transposition_that_the_robust_statistic_undoes():
    # Shortest and intermediate sides almost equal: tiny noise swaps them.
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 0.80]])
    a = tri + [[0, 0], [0, 0], [-0.02, 0]]
    b = (tri + [[0, 0], [0, 0], [0.02, 0]]) @ mm.rotation(0.4).T
    pa, pb = groth_order(a[None])[0], groth_order(b[None])[0]
    ca, cb = a[pa][None], b[pb][None]
    # Same landmarks, different Groth order, and the orders differ by a swap.
    assert not np.array_equal(pa, pb)
    assert np.sign(np.linalg.det(np.eye(3)[pa])) != np.sign(np.linalg.det(np.eye(3)[pb]))
    sigma = 0.01
    plain = mm.glrt(ca, cb, sigma)[0, 0]
    robust = mm.glrt(ca, cb, sigma, cyclic=True)[0, 0]
    assert plain < -100 and robust > -10
    # Cyclic shifts of the Groth order alone would not help.
    best_shift = max(mm.glrt(ca, np.roll(cb, -s, axis=1), sigma)[0, 0] for s in range(3))
    assert best_shift < -100


def test_robust_statistic_never_loses_on_same_orientation_pairs(rng):
    cp = mm.triangulate(rng.uniform(0, 5, (40, 2))).coords
    cq = mm.triangulate(rng.uniform(0, 5, (40, 2))).coords
    plain, robust = mm.glrt(cp, cq, 0.1), mm.glrt(cp, cq, 0.1, cyclic=True)
    same = (ccw_order(cp)[:, 1] == 1)[:, None] == (ccw_order(cq)[:, 1] == 1)[None, :]
    assert np.all(robust[same] >= plain[same] - 1e-9)


def test_cyclic_method_detects_more_than_paper():
    gain = 0
    for seed in range(6):
        sc = mm.simulate.make_pair(100, 0.75, 40, rng=seed)
        gain += _counts(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method="cyclic"))["tp"]
        gain -= _counts(sc, mm.merge_maps(sc.p, sc.q, sc.sigma, method="paper"))["tp"]
    assert gain > 0


def _reject_one_at_a_time(P, Q, pairs, sigma, gate_p):
    """Groth's rule written out for one map pair: refit, drop the worst outside the gate, repeat."""
    from scipy.special import chdtri

    from mapmerge.alignment import align_pairs, prediction_var, rotate

    while len(pairs) >= 3:
        al = align_pairs(P[pairs[:, 0]], Q[pairs[:, 1]], sigma)
        var = 2 * sigma**2 + prediction_var(P[pairs[:, 0]], al)
        resid = np.sum((Q[pairs[:, 1]] - rotate(al.theta, P[pairs[:, 0]]) - al.t) ** 2, axis=1) / var
        if resid.max() <= chdtri(2, gate_p):
            break
        pairs = np.delete(pairs, np.argmax(resid), axis=0)
    return pairs


def test_outlier_rejection_of_many_map_pairs_at_once_follows_the_rule_per_pair(rng):
    from mapmerge.alignment import reject_outliers, reject_outliers_batch

    B, n = 60, 25
    P = rng.uniform(0, 10, (B, n, 2))
    sigma = 10 ** rng.uniform(-2.5, -0.5, B)
    theta, t = rng.uniform(-np.pi, np.pi, B), rng.normal(0, 5, (B, 2))
    Q = mm.alignment.rotate(theta, P) + t[:, None] + sigma[:, None, None] * rng.standard_normal((B, n, 2))
    parts = []
    for b in range(B):
        m = rng.integers(0, n + 1)  # some map pairs with fewer than 3 pairs: nothing to reject
        p_idx = rng.permutation(n)[:m]
        q_idx = np.where(rng.random(m) < rng.uniform(0, 0.6), rng.integers(0, n, m), p_idx)  # wrong partners
        parts.append(np.stack([p_idx, q_idx], axis=1).reshape(-1, 2))
    trial = np.repeat(np.arange(B), [len(x) for x in parts])
    pairs = np.concatenate(parts)
    keep = reject_outliers_batch(P, Q, trial, pairs, sigma, 1e-3)
    dropped = 0
    for b in range(B):
        expected = _reject_one_at_a_time(P[b], Q[b], parts[b], sigma[b], 1e-3)
        np.testing.assert_array_equal(pairs[keep & (trial == b)], expected)
        np.testing.assert_array_equal(reject_outliers(P[b], Q[b], parts[b], sigma[b]), expected)
        dropped += len(parts[b]) - len(expected)
    assert dropped > 50  # the rule had work to do


def test_many_fits_covariances_and_prediction_variances_equal_one_fit_at_a_time(rng):
    """The vectorised (θ, t) covariances and prediction variances of ragged fits (consensus's refits,
    Groth's rejection) equal each fit's own ``Alignment.cov`` and ½ tr(G Σ Gᵀ), G = [R J x, I]."""
    from mapmerge.alignment import (ROT90, align_pairs, prediction_var, prediction_vars, rotation,
                                    transform_covariances)

    F, sigma = 7, 0.05
    sizes = rng.integers(3, 12, F)
    sizes[2] = 1  # too few pairs to fit: left out
    fits, mu, owner = [], [], []
    for f, m in enumerate(sizes):
        P = rng.uniform(-5, 5, (m, 2))
        Q = mm.alignment.rotate(rng.uniform(-np.pi, np.pi), P) + rng.normal(0, 3, 2) + rng.normal(0, sigma, (m, 2))
        al = align_pairs(P, Q, sigma)
        fits.append(al)
        mu.append(al.mu)
        owner.append(np.full(m, f))
    fitted = sizes >= 3
    theta = np.array([al.theta for al in fits])
    cov = transform_covariances(np.concatenate(owner), np.concatenate(mu), theta, sigma, fitted)
    x = rng.uniform(-8, 8, (4, 3, 2))
    var = prediction_vars(x[None], theta[fitted], cov[fitted])
    for k, f in enumerate(np.flatnonzero(fitted)):
        al = fits[f]
        np.testing.assert_allclose(cov[f], al.cov, rtol=1e-10, atol=1e-18)
        G = np.concatenate([(x @ (rotation(al.theta) @ ROT90).T)[..., None],
                            np.broadcast_to(np.eye(2), x.shape + (2,))], axis=-1)
        expected = 0.5 * np.trace(G @ al.cov @ np.swapaxes(G, -1, -2), axis1=-2, axis2=-1)
        np.testing.assert_allclose(var[k], expected, rtol=1e-10)
        np.testing.assert_allclose(prediction_var(x, al), expected, rtol=1e-10)
