"""merge_many: N maps into one frame (mapmerge.group), make_group and group_errors."""

import re
from pathlib import Path

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import group
from mapmerge.simulate import ScenarioError


def _variances(team):
    return [np.broadcast_to(team.sigma**2 * np.eye(2), (len(m), 2, 2)) for m in team.maps]


def _true_edges(team, pairs):
    """Edges from the true correspondences, each fitted by the n-point closed form."""
    edges = []
    for i, j in pairs:
        _, a, b = np.intersect1d(team.ids[i], team.ids[j], return_indices=True)
        al = mm.align(team.maps[i][a], team.maps[j][b], team.sigma)
        edges.append(group.Edge(i, j, group.ACCEPTED, al.theta, al.t, al.cov, np.stack([a, b], axis=1)))
    return edges


def test_two_maps_are_the_pairwise_closed_form():
    sc = mm.simulate.make_pair(100, 0.75, 30, rng=0)
    res = mm.merge_maps(sc.p, sc.q, sc.sigma)
    g = mm.merge_many([sc.p, sc.q], sc.sigma)
    assert g.placed.all() and g.reference == 0
    assert g.theta[1] == pytest.approx(res.theta, abs=1e-12)
    np.testing.assert_allclose(g.t[1], res.t, atol=1e-12)
    np.testing.assert_allclose(g.frame_cov[1], res.alignment.cov, rtol=1e-9, atol=1e-18)
    assert len(g.merged) == len(res.merged)
    # Every combined-map row and covariance, matched through the source rows.
    row_of = {(int(a), int(b)): k for k, (a, b) in enumerate(g.tracks)}
    k = [row_of[(int(a), int(b))] for a, b in zip(res.index_p, res.index_q)]
    np.testing.assert_allclose(g.merged[k], res.merged, atol=1e-12)
    np.testing.assert_allclose(g.merged_cov[k], res.cov, rtol=1e-9, atol=1e-18)


def test_ring_team_with_a_stranger():
    team = mm.simulate.make_group(5, 60, 0.5, 25, topology="ring", n_strangers=1, rng=3)
    for placement in group.PLACEMENTS:
        g = mm.merge_many(team.maps, team.sigma, placement=placement)
        err = mm.metrics.group_errors(team, g)
        assert err["status"][:5] == ["correct"] * 5, placement
        assert not g.placed[5] and err["strangers_placed"] == 0 and err["all_correct"]
        assert np.all(g.tracks[:, 5] == -1)
        # Every landmark of a placed map is in exactly one track.
        for i in range(5):
            assert np.array_equal(np.sort(g.tracks[g.tracks[:, i] >= 0, i]), np.arange(len(team.maps[i])))
        assert err["track_purity"] > 0.9 and err["fused_rmse"] < team.sigma
    assert {e.status for e in g.edges} <= {group.ACCEPTED, group.NO_MATCH}


def test_a_wrong_edge_is_refused_by_the_cycle_test():
    team = mm.simulate.make_group(4, 60, 0.6, 30, topology="ring", rng=1)
    edges = _true_edges(team, [(0, 1), (1, 2), (2, 3), (0, 3)])
    # The strongest edge, turned by 5 degrees: the only way to notice is around the cycle.
    strongest = max(range(4), key=lambda k: len(edges[k].pairs))
    e = edges[strongest]
    edges[strongest] = group.Edge(e.i, e.j, e.status, e.theta + np.radians(5), e.t, e.cov, e.pairs)
    joint = group.assemble(team.maps, _variances(team), edges, 0, "joint")
    statuses = [x.status for x in joint.edges]
    assert statuses.count(group.INCONSISTENT) == 1
    assert mm.metrics.group_errors(team, joint)["all_correct"]
    tree = group.assemble(team.maps, _variances(team), edges, 0, "tree")
    assert mm.metrics.group_errors(team, tree)["placed_wrong"] >= 1


def test_joint_covariances_agree_with_monte_carlo():
    team = mm.simulate.make_group(3, 30, 0.6, 30, topology="chain", rng=5)
    pairs = [(0, 1), (1, 2), (0, 2)]
    truth = [mm.rotation(th) @ team.truth[ids].T for th, ids in zip(team.theta, team.ids)]
    rng = np.random.default_rng(12)
    estimates, predicted = [], []
    for _ in range(1000):
        maps = [(x.T + t) + team.sigma * rng.standard_normal(x.T.shape) for x, t in zip(truth, team.t)]
        noisy = mm.simulate.Team(maps, team.ids, team.truth, team.theta, team.t, team.sigma, team.covs,
                                 team.stranger, team.centres, team.snr_db, team.topology)
        g = group.assemble(maps, _variances(team), _true_edges(noisy, pairs), 0, "joint")
        # Frames 1 and 2 (θ, t), then the first five fused landmarks (x, y).
        estimates.append(np.concatenate([g.theta[1:], g.t[1:].ravel(), g.merged[:5].ravel()]))
        predicted.append(np.concatenate([g.frame_cov[1:, 0, 0], np.diagonal(g.frame_cov[1:, 1:, 1:], axis1=1,
                                                                                 axis2=2).ravel(),
                                         np.diagonal(g.merged_cov[:5], axis1=1, axis2=2).ravel()]))
    assert np.all((g.tracks[:5] >= 0).sum(axis=1) >= 2)
    empirical = np.var(np.array(estimates), axis=0)
    np.testing.assert_allclose(empirical, np.mean(predicted, axis=0), rtol=0.1)


def test_unplaced_reference_moves_the_frame_to_the_largest_group():
    team = mm.simulate.make_group(3, 50, 0.5, 30, topology="chain", n_strangers=1, rng=2)
    maps = [team.maps[3]] + team.maps[:3]
    g = mm.merge_many(maps, team.sigma)
    assert g.reference == 1 and not g.placed[0] and g.placed[1:].all()
    assert g.theta[1] == 0 and np.all(g.frame_cov[1] == 0)


def test_candidates_keep_the_neighbours_of_a_chain():
    team = mm.simulate.make_group(14, 100, 0.5, 30, topology="chain", rng=0)
    assert len(group.candidate_pairs(team.maps, np.full(14, team.sigma))) == 14 * 13 // 2
    pairs = group.candidate_pairs(team.maps, np.full(14, team.sigma), candidates=3)
    assert len(pairs) < 14 * 13 // 2
    chosen = {tuple(p) for p in pairs.tolist()}
    assert all((i, i + 1) in chosen for i in range(13))


def test_per_map_sigma_and_covariances():
    team = mm.simulate.make_group(3, 50, 0.5, 30, topology="chain", rng=4)
    by_sigma = mm.merge_many(team.maps, [team.sigma] * 3)
    by_cov = mm.merge_many(team.maps, covs=[np.full(len(m), team.sigma**2) for m in team.maps])
    assert by_sigma.placed.all() and by_cov.placed.all()
    np.testing.assert_allclose(by_cov.theta, by_sigma.theta, atol=1e-9)


def test_make_group_topologies_and_reproducibility():
    for topology in mm.simulate.TOPOLOGIES:
        team = mm.simulate.make_group(6, 80, 0.5, 20, topology=topology, n_strangers=1, rng=7)
        again = mm.simulate.make_group(6, 80, 0.5, 20, topology=topology, n_strangers=1, rng=7)
        assert all(np.array_equal(a, b) for a, b in zip(team.maps, again.maps))
        assert team.stranger.tolist() == [False] * 6 + [True]
        assert not np.intersect1d(team.ids[6], np.concatenate(team.ids[:6])).size
        for i in range(6):
            x = mm.rotation(team.theta[i]) @ team.truth[team.ids[i]].T
            assert np.std(team.maps[i] - x.T - team.t[i]) == pytest.approx(team.sigma, rel=0.25)
    ring = mm.simulate.make_group(8, 200, 0.5, 20, topology="ring", rng=0)
    # Neighbours (the last and the first included) share about half of a disc's landmarks.
    shared = [len(np.intersect1d(ring.ids[i], ring.ids[(i + 1) % 8])) for i in range(8)]
    assert 70 < np.mean(shared) < 130


@pytest.mark.parametrize("kwargs, argument", [
    ({"n_agents": 1}, "n_agents"), ({"overlap": 1.0}, "overlap"), ({"topology": "mesh"}, "topology"),
    ({"n_strangers": -1}, "n_strangers"), ({"n_landmarks": 2}, "n_landmarks"), ({"layout": "grid"}, "layout"),
])
def test_make_group_refuses_bad_arguments(kwargs, argument):
    with pytest.raises(ScenarioError, match=argument):
        mm.simulate.make_group(**kwargs)


@pytest.mark.parametrize("kwargs, message", [
    ({"maps": "one"}, "maps must be a list"),
    ({"sigma": [0.1, 0.1]}, r"one per map \(3,\)"),
    ({"sigma": -1}, "sigma must be a positive"),
    ({"sigma": None}, "sigma is needed"),
    ({"reference": 3}, "reference must be"),
    ({"placement": "star"}, "placement must be"),
    ({"candidates": 0}, "candidates must be"),
    ({"n_jobs": 0}, "n_jobs must be"),
    ({"method": "nope"}, "method must be"),
    ({"covs": [None]}, "covs must be a list of 3"),
])
def test_merge_many_refuses_bad_arguments(kwargs, message):
    team = mm.simulate.make_group(3, 30, 0.5, 30, topology="chain", rng=0)
    args = {"maps": team.maps, "sigma": team.sigma, **kwargs}
    with pytest.raises(ValueError, match=message):
        mm.merge_many(**args)


def test_merge_many_names_a_bad_map():
    team = mm.simulate.make_group(3, 30, 0.5, 30, topology="chain", rng=0)
    maps = list(team.maps)
    maps[2] = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    with pytest.raises(ValueError, match=r"maps\[2\] points are all collinear"):
        mm.merge_many(maps, team.sigma)


def test_the_readme_team_example_prints_what_the_readme_shows(capsys):
    section = (Path(__file__).resolve().parents[1] / "README.md").read_text().split("## Many agents")[1]
    code = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)
    shown = re.search(r"prints\n\n```\n(.*?)```", section, re.DOTALL).group(1)
    exec(code, {})
    assert capsys.readouterr().out == shown


def test_joint_ml_is_the_least_squares_optimum():
    """The Gauss-Newton solution against scipy's least_squares on the same observations (no Huber weight
    is active at this SNR)."""
    from scipy.optimize import least_squares

    team = mm.simulate.make_group(3, 40, 0.6, 30, topology="chain", rng=8)
    g = group.assemble(team.maps, _variances(team), _true_edges(team, [(0, 1), (1, 2), (0, 2)]), 0, "joint")
    multi = (g.tracks >= 0).sum(axis=1) >= 2
    k, owner = np.nonzero(g.tracks[multi] >= 0)
    z = np.stack([team.maps[i][r] for i, r in zip(owner, g.tracks[multi][k, owner])])

    def residuals(v):
        poses = np.concatenate([np.zeros(3), v[:6]]).reshape(3, 3)
        x = v[6:].reshape(-1, 2)
        return ((mm.alignment.rotate(poses[owner, 0], x[k][:, None])[:, 0] + poses[owner, 1:] - z)
                / team.sigma).ravel()

    start = np.concatenate([np.concatenate([g.theta[1:, None], g.t[1:]], axis=1).ravel(), g.merged[multi].ravel()])
    start[:6] += 1e-3  # away from the answer, so that least_squares has work to do
    ls = least_squares(residuals, start, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(ls.x[:6], start[:6] - 1e-3, atol=1e-9)
    np.testing.assert_allclose(ls.x[6:], g.merged[multi].ravel(), atol=1e-9)
