"""The MR.CLAM loader: each robot's own iSAM2 map of the first minute, checked against the surveyed landmarks."""

import gzip
import importlib.util
import shutil
from pathlib import Path

import numpy as np
import pytest

import mapmerge as mm
from mapmerge import mrclam
from mapmerge.datasets import MRCLAM_DIR, DatasetError, load_mrclam

pytest.importorskip("gtsam")

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One fresh solve cache for the module: the first minute is solved once, then read back."""
    root = tmp_path_factory.mktemp("mrclam_cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MAPMERGE_CACHE", str(root))
        yield root


@pytest.fixture(scope="module")
def first_minute(cache):
    return mm.datasets.mrclam(robots=(3, 2), until_s=60)


def _derivation_script():
    spec = importlib.util.spec_from_file_location("derive_mrclam", ROOT / "tools" / "derive_mrclam.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_maps_are_in_each_robots_first_pose_frame_and_fit_the_surveyed_landmarks(first_minute):
    team = first_minute
    assert team.robots == (3, 2) and len(team.maps) == 2
    for i in range(2):
        ids, points, cov = team.ids[i], team.maps[i], team.covs[i]
        # Landmark subjects only (6-20), sorted, each surveyed; no robot (1-5) in a map.
        assert np.all(np.diff(ids) > 0) and ids.min() >= 6 and ids.max() <= 20
        assert not np.any(np.isnan(team.truth[ids])) and np.all(np.isnan(team.truth[:6]))
        assert points.shape == (len(ids), 2) and cov.shape == (len(ids), 2, 2)
        # Positive definite, and at least the calibrated systematic error that sightings do not average away.
        floor = team.calibrations[i].landmark_sigma ** 2
        assert floor > 0
        assert np.all(np.linalg.eigvalsh(cov) >= floor) and np.all(np.linalg.eigvalsh(team.shape_covs[i]) >= floor)
        # The surveyed landmarks seen from the robot's true first pose: a minute of driving drifts little.
        x, y, heading = team.first_poses[i]
        in_robot_frame = (team.truth[ids] - [x, y]) @ mm.rotation(heading)
        assert np.max(np.hypot(*(points - in_robot_frame).T)) < 0.6
        # The fit by ids is that frame to a few degrees, in the convention map ≈ R(θ) world + t.
        assert abs(np.degrees(mm.wrap_angle(team.theta[i] + heading))) < 5
        fitted = team.truth[ids] @ mm.rotation(team.theta[i]).T + team.t[i]
        assert np.sqrt(np.mean(np.sum((fitted - points) ** 2, axis=1))) == pytest.approx(team.rms[i])
    # Measured 0.082 m for robot 3 (14 landmarks) and 0.232 m for robot 2 (10) after 60 s.
    assert team.rms[0] < 0.12 and team.rms[1] < 0.3
    assert np.all(team.sigma > 0) and not np.any(team.stranger)


def test_until_s_keeps_the_sightings_of_that_time(first_minute):
    recording = load_mrclam(robots=(3,))
    sightings = recording.robots[3].sightings
    first = recording.robots[3].odometry[0, 0]
    kept = (sightings[:, 0] >= first) & (sightings[:, 0] <= recording.start + 60)
    assert first_minute.sightings[0] == kept.sum()
    assert set(first_minute.ids[0]) == set(sightings[kept, 1].astype(int))


def test_an_original_format_directory_gives_the_same_maps(tmp_path, monkeypatch, first_minute):
    monkeypatch.setenv("MAPMERGE_CACHE", str(tmp_path / "own_cache"))  # solved again, not read back
    original = tmp_path / "original"
    original.mkdir()
    for packed in MRCLAM_DIR.glob("*.dat.gz"):
        with gzip.open(packed, "rb") as src, open(original / packed.name[:-3], "wb") as dst:
            shutil.copyfileobj(src, dst)
    team = mm.datasets.mrclam(path=original, robots=(2,), until_s=60)
    np.testing.assert_array_equal(team.ids[0], first_minute.ids[1])
    np.testing.assert_allclose(team.maps[0], first_minute.maps[1], atol=1e-9)
    np.testing.assert_allclose(team.covs[0], first_minute.covs[1], atol=1e-12)
    assert any((tmp_path / "own_cache").rglob("*.pkl"))


def test_the_derivation_script_rebuilds_the_bundle(tmp_path):
    """The bundle is the derivation's fixed point: its files, unpacked and derived again, give the same bytes."""
    derive = _derivation_script()
    original = tmp_path / "original"
    original.mkdir()
    for packed in MRCLAM_DIR.glob("*.dat.gz"):
        (original / packed.name[:-3]).write_bytes(gzip.decompress(packed.read_bytes()))
    derive.derive(original, tmp_path / "bundle")
    for packed in MRCLAM_DIR.glob("*.dat.gz"):
        assert (tmp_path / "bundle" / packed.name).read_bytes() == packed.read_bytes(), packed.name


def test_thinned_odometry_integrates_to_the_same_motion():
    derive = _derivation_script()
    rng = np.random.default_rng(7)
    # Commands held for runs of lines, some time stamps repeated, as in the logs.
    t = np.cumsum(rng.choice([0.0, 0.01, 0.02], size=400, p=[0.05, 0.75, 0.2]))
    runs = np.repeat(rng.normal(0, [0.1, 0.4], size=(40, 2)), 10, axis=0)
    odometry = np.column_stack([t, runs])
    kept = odometry[derive.thin_odometry(odometry)]
    assert len(kept) < len(odometry) / 5
    times = np.linspace(t[0], t[-1], 50)
    full = mrclam.dead_reckon(odometry[np.r_[np.diff(t) > 0, True]], times)
    np.testing.assert_allclose(mrclam.dead_reckon(kept, times), full, atol=1e-12)


def test_pose_times_cover_every_sighting_without_near_duplicates():
    sightings = np.array([0.3, 0.3, 1.02, 2.5, 6.0])
    times = mrclam.pose_times(0.0, 6.2, sightings)
    assert np.isin(sightings, times).all() and times[0] == 0.0 and times[-1] == 6.2
    assert np.diff(times).max() <= mrclam.MAX_POSE_GAP and np.diff(times).min() >= mrclam.MIN_POSE_GAP - 1e-12
    assert 1.0 not in times  # the grid time 0.02 s before a sighting is left out


@pytest.mark.parametrize("kwargs, message", [
    ({"robots": (0, 1)}, "robots must be distinct robot numbers"),
    ({"robots": (2, 2)}, "robots must be distinct robot numbers"),
    ({"robots": ()}, "robots must be distinct robot numbers"),
    ({"robots": 3}, "robots must be distinct robot numbers"),
    ({"until_s": 0}, "until_s must be a positive number"),
    ({"until_s": -5.0}, "until_s must be a positive number"),
    ({"until_s": float("nan")}, "until_s must be a positive number"),
    ({"until_s": True}, "until_s must be a positive number"),
    ({"until_s": 7.0, "robots": (3,)}, "leaves robot 3 with fewer than 2 landmarks"),
])
def test_bad_arguments_are_one_line_errors(cache, kwargs, message):
    with pytest.raises(ValueError, match=message) as info:
        mm.datasets.mrclam(**kwargs)
    assert "\n" not in str(info.value)


def test_missing_directory_or_file_is_a_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match="MR.CLAM directory not found"):
        mm.datasets.mrclam(path=tmp_path / "nowhere")
    shutil.copy(MRCLAM_DIR / "Barcodes.dat.gz", tmp_path)
    with pytest.raises(DatasetError, match=r"MR.CLAM file not found: .*Landmark_Groundtruth.dat"):
        mm.datasets.mrclam(path=tmp_path)


def test_solves_are_cached_on_disk(cache, first_minute):
    assert any(cache.rglob("*.pkl"))
    again = mm.datasets.mrclam(robots=(3, 2), until_s=60)
    np.testing.assert_array_equal(again.maps[0], first_minute.maps[0])
