"""The Victoria Park loader and a real two-agent merge."""

import shutil

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import metrics
from mapmerge.datasets import DATA_DIR, DatasetError, load_log, victoria_park


def test_log_counts():
    log = load_log()
    assert len(log.pose_ids) == 6969 and log.trajectory.shape == (6968, 3)
    assert log.trees.shape == (151, 2) and log.obs_xy.shape == (3640, 2)
    assert log.obs_tree.max() == 150


def test_cut_before_pose_3484_gives_82_135_66():
    vp = victoria_park(cut=3483)
    assert (len(vp.p), len(vp.q), vp.n_common) == (82, 135, 66)
    assert vp.poses_p == 3483


def test_agent_maps_and_true_transform_are_consistent():
    vp = victoria_park(cut=3483)
    common, ip, iq = np.intersect1d(vp.ids_p, vp.ids_q, return_indices=True)
    pred = vp.p[ip] @ mm.rotation(vp.theta).T + vp.t
    # Each agent's map sits on the reference trees to a few decimetres.
    assert np.sqrt(np.mean((vp.p - vp.truth[vp.ids_p]) ** 2)) < 0.5
    assert np.sqrt(np.mean((vp.q[iq] - pred) ** 2)) < 1.0
    assert 0.05 < vp.sigma < 1.0


@pytest.mark.parametrize("method", ["consensus", "groth"])
def test_merge_recovers_true_transform(method):
    vp = victoria_park(cut=3483)
    res = mm.merge_maps(vp.p, vp.q, vp.sigma, method=method)
    err = metrics.map_errors(vp, res)
    print(method, err)
    assert err["rot_err_deg"] < 1.0 and err["trans_err"] < 1.0
    assert err["correct_pairs"] >= 40


def test_slam_source_reports_marginal_covariances():
    pytest.importorskip("gtsam")
    vp = victoria_park(cut=3483, source="slam")
    assert (len(vp.p), len(vp.q), vp.n_common) == (82, 135, 66)
    assert vp.cov_p.shape == (82, 2, 2) and np.all(np.linalg.eigvalsh(vp.cov_p) > 0)
    # Anchored at its first pose, an agent is surest of the trees it saw first.
    first_tree = vp.ids_p == load_log().obs_tree[0]
    assert np.trace(vp.cov_p[first_tree][0]) < np.median(np.trace(vp.cov_p, axis1=1, axis2=2))


def test_bad_arguments_and_files(tmp_path):
    with pytest.raises(ValueError, match="cut"):
        victoria_park(cut=0)
    with pytest.raises(ValueError, match="source"):
        victoria_park(source="lidar")
    with pytest.raises(DatasetError, match="not found"):
        victoria_park(path=tmp_path)
    for name in ("victoria_park.txt", "ISAM2_GT_victoriaPark.txt", "ISAM2_GT_victoriaPark_lm.txt"):
        shutil.copy(DATA_DIR / name, tmp_path / name)
    with open(tmp_path / "victoria_park.txt", "a") as fh:
        fh.write("LANDMARK 12 oops 1 2 0.4 0 0.4\n")
    with pytest.raises(DatasetError, match=r"victoria_park.txt:10609"):
        victoria_park(path=tmp_path)
    (tmp_path / "victoria_park.txt").write_text((DATA_DIR / "victoria_park.txt").read_text())
    (tmp_path / "ISAM2_GT_victoriaPark_lm.txt").write_text("1 2\n3 4\n")
    with pytest.raises(DatasetError, match="151"):
        victoria_park(path=tmp_path)
