"""Matching: τ forms (mapmerge.matching), the LP (mapmerge.assignment), correspondences and their conflict
rule (mapmerge.correspondence)."""

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import correspondence
from mapmerge.assignment import assign, assign_sparse, local_numbering
from mapmerge.correspondence import correspondences, resolve_correspondences

from lp_reference import lapjvsp_assign


def test_threshold_forms():
    assert mm.resolve_log_tau("chi2:0.05") == pytest.approx(-0.5 * 7.814727903251178)
    assert mm.resolve_log_tau(-3) == -3.0
    assert mm.resolve_log_tau("-2.5") == -2.5
    assert mm.resolve_log_tau(float("-inf")) == -np.inf
    for bad in ("chi2:1.5", "chi2:x", "oracle", float("nan"), None):
        with pytest.raises(ValueError, match="tau"):
            mm.resolve_log_tau(bad)


def _sequential_greedy(vertices_p, vertices_q, log_lr, min_votes=1):
    """The documented rule, one candidate at a time (most votes, best score, lowest indices), among the
    candidates with at least ``min_votes`` votes."""
    cand = {}
    for tp, tq, s in zip(vertices_p, vertices_q, log_lr):
        for i, j in zip(tp, tq):
            votes, best = cand.get((i, j), (0, -np.inf))
            cand[(i, j)] = (votes + 1, max(best, s))
    cand = {k: v for k, v in cand.items() if v[0] >= min_votes}
    used_p, used_q, keep = set(), set(), []
    for (i, j), _ in sorted(cand.items(), key=lambda kv: (-kv[1][0], -kv[1][1], kv[0][0], kv[0][1])):
        if i not in used_p and j not in used_q:
            used_p.add(i), used_q.add(j), keep.append((i, j))
    return sorted(keep), len(cand) - len(keep)


@pytest.mark.parametrize("min_votes", [1, 2])
@pytest.mark.parametrize("scored", [True, False])
@pytest.mark.parametrize("key_table_factor", [0, 10**9], ids=["sorted-keys", "key-table"])
def test_correspondences_equal_the_sequential_greedy(monkeypatch, key_table_factor, scored, min_votes):
    """Both ways of grouping candidates (a sort, a table of keys) give the rule's answer, with
    scores and by votes alone, and among the candidates with two votes or more (Groth's); the landmark
    indices carry offsets as a batch of map pairs has."""
    monkeypatch.setattr(correspondence, "KEY_TABLE_FACTOR", key_table_factor)
    rng = np.random.default_rng(7)
    for _ in range(1500):
        m, n = int(rng.integers(1, 12)), int(rng.integers(3, 25) if min_votes == 1 else rng.integers(3, 8))
        vp = np.array([rng.choice(n, 3, replace=False) for _ in range(m)]) + 40 * int(rng.integers(0, 3))
        vq = np.array([rng.choice(n, 3, replace=False) for _ in range(m)]) + 40 * int(rng.integers(0, 3))
        scores = np.round(rng.normal(size=m), 1) if scored else np.zeros(m)  # ties in score happen
        uniq, keep, votes = resolve_correspondences(vp, vq, scores if scored else None, min_votes)
        expected, dropped = _sequential_greedy(vp, vq, scores, min_votes)
        assert [tuple(p) for p in uniq[keep].tolist()] == expected
        assert np.count_nonzero((votes >= min_votes) & ~keep) == dropped
        counted = {}
        for i, j in zip(vp.ravel().tolist(), vq.ravel().tolist()):
            counted[(i, j)] = counted.get((i, j), 0) + 1
        assert dict(zip(map(tuple, uniq.tolist()), votes.tolist())) == counted
        assert list(map(tuple, uniq.tolist())) == sorted(counted)
        if scored and min_votes == 1:
            assert correspondences(vp, vq, scores)[1] == dropped


def test_lp_objectives_and_the_sparse_lp_agree_with_brute_force(rng):
    """The LP's tentative pairs are the best one-to-one assignment (objectives Σ Λ and Σ log Λ)."""
    from itertools import permutations

    for _ in range(30):
        log_lr = -rng.exponential(2.0, size=(4, 5))
        for objective, weight in (("lr", np.exp(log_lr)), ("loglr", log_lr)):
            best = max(permutations(range(5), 4), key=lambda cols: weight[np.arange(4), cols].sum())
            np.testing.assert_array_equal(assign(log_lr, objective), np.stack([np.arange(4), best], axis=1))
        # With every pair a candidate, the sparse LP (each row free to stay unpaired at Λ = 0) pairs every
        # row as the dense LP does.
        cand = np.argwhere(np.ones((4, 5), bool))
        chosen = assign_sparse(log_lr[cand[:, 0], cand[:, 1]], cand, (4, 5), "lr")
        np.testing.assert_array_equal(chosen, assign(log_lr, "lr"))


@pytest.mark.parametrize("objective", ["lr", "loglr"])
def test_sparse_lp_is_the_maximum_weight_matching_of_scipys_solver(rng, objective):
    """The min-cost flow of ``assign_sparse`` against scipy's exact sparse assignment (LAPJVsp) on random
    sparse graphs with one giant component."""
    for _ in range(20):
        n_p, n_q = 60, 70
        pairs = np.unique(np.stack([rng.integers(0, n_p, 400), rng.integers(0, n_q, 400)], axis=1), axis=0)
        log_lr = -rng.exponential(3.0, size=len(pairs))
        np.testing.assert_array_equal(assign_sparse(log_lr, pairs, (n_p, n_q), objective),
                                      lapjvsp_assign(log_lr, pairs, (n_p, n_q), objective))


def test_local_numbering_numbers_every_node_once_and_keeps_neighbours_close(rng):
    """p triangles get 0..n_p-1 and q triangles n_p..n_p+n_q-1, each once (isolated ones too), and on a chain
    scattered by a random order the numbering undoes the scatter."""
    n_p, n_q = 60, 70
    pairs = np.unique(np.stack([rng.integers(0, n_p - 5, 150), rng.integers(0, n_q - 5, 150)], axis=1), axis=0)
    p_node, q_node = local_numbering(pairs, n_p, n_q)
    np.testing.assert_array_equal(np.sort(p_node), np.arange(n_p))
    np.testing.assert_array_equal(np.sort(q_node), n_p + np.arange(n_q))
    # A path p0-q0-p1-q1-... under random labels: its arcs join nodes 1 apart in the numbering's p/q ranks.
    n = 200
    perm_p, perm_q = rng.permutation(n), rng.permutation(n)
    chain = np.concatenate([np.stack([perm_p, perm_q], axis=1), np.stack([perm_p[1:], perm_q[:-1]], axis=1)])
    p_node, q_node = local_numbering(chain, n, n)
    assert np.abs(p_node[chain[:, 0]] - (q_node[chain[:, 1]] - n)).max() <= 1
    assert np.abs(chain[:, 0] - chain[:, 1]).max() > 100


def test_correspondences_count_the_dropped_rivals():
    pairs, n_conflicts = correspondences(np.array([[0, 1, 2], [0, 1, 3]]), np.array([[5, 6, 7], [5, 6, 8]]),
                                         np.array([-1.0, -2.0]))
    np.testing.assert_array_equal(pairs, [[0, 5], [1, 6], [2, 7], [3, 8]])
    assert n_conflicts == 0
    pairs, n_conflicts = correspondences(np.array([[0, 1, 2], [0, 1, 2]]), np.array([[5, 6, 7], [5, 6, 8]]),
                                         np.array([-1.0, -2.0]))
    np.testing.assert_array_equal(pairs, [[0, 5], [1, 6], [2, 7]])  # the better-scored triangle wins landmark 2
    assert n_conflicts == 1


def test_candidate_components_are_the_connected_components_of_the_candidate_graph():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from mapmerge.assignment import LABEL_SWEEPS, candidate_components

    rng = np.random.default_rng(5)
    chain = np.arange(4 * LABEL_SWEEPS)  # p0-q0-p1-q1-...: too long for the sweeps, so scipy decides
    cases = [(chain[:-1] // 2 + chain[:-1] % 2, chain[:-1] // 2, 3 * LABEL_SWEEPS, 3 * LABEL_SWEEPS)]
    for _ in range(200):
        n_p, n_q, m = rng.integers(1, 30), rng.integers(1, 30), rng.integers(1, 40)
        cases.append((rng.integers(0, n_p, m), rng.integers(0, n_q, m), n_p, n_q))
    for i, j, n_p, n_q in cases:
        label = candidate_components(i, j, n_p, n_q)
        graph = coo_matrix((np.ones(i.size), (i, n_p + j)), shape=(n_p + n_q,) * 2)
        truth = connected_components(graph, directed=False)[1][i]
        # The same partition of the candidates, whatever the numbering.
        assert np.array_equal(label[:, None] == label[None], truth[:, None] == truth[None])


def test_component_blocks_hold_each_components_candidates_between_its_sorted_rows_and_columns():
    from mapmerge.assignment import candidate_components, component_blocks

    rng = np.random.default_rng(6)
    for _ in range(200):
        n_p, n_q = rng.integers(1, 30, 2)
        pairs = np.unique(np.stack([rng.integers(0, n_p, 40), rng.integers(0, n_q, 40)], 1)[:rng.integers(0, 40)],
                          axis=0)
        pairs = pairs[rng.permutation(len(pairs))]
        i, j, values = pairs[:, 0], pairs[:, 1], rng.random(len(pairs))
        component = candidate_components(i, j, n_p, n_q)
        blocks = list(component_blocks(i, j, values, component, -1.0))
        # One block per component, in the order of the components' labels.
        assert len(blocks) == np.unique(component).size
        for label, (rows, cols, block) in zip(np.unique(component), blocks):
            sel = component == label
            np.testing.assert_array_equal(rows, np.unique(i[sel]))
            np.testing.assert_array_equal(cols, np.unique(j[sel]))
            expected = np.full((rows.size, cols.size), -1.0)
            expected[np.searchsorted(rows, i[sel]), np.searchsorted(cols, j[sel])] = values[sel]
            np.testing.assert_array_equal(block, expected)


def test_the_lp_names_an_unknown_objective():
    for solve in (lambda: assign(np.zeros((3, 3)), "max"),
                  lambda: assign_sparse(np.zeros(2), np.array([[0, 0], [1, 1]]), (2, 2), "max")):
        with pytest.raises(ValueError, match=r"objective must be one of \('lr', 'loglr'\), got 'max'"):
            solve()
