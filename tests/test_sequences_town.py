"""The built-in town (core/sim/town/): deterministic simulated HDL-64E scans, a realistic
drive with a loop, poses consistent with the scans, and the town laid along real KITTI
trajectories."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from lidarloc.core.config import TownConfig
from lidarloc.core.errors import DataError
from lidarloc.core.geometry import inv_pose, pose_to_xyz_ypr
from lidarloc.core.sequences.kitti_io import cam0_to_lidar_poses, read_pose_lines, read_tr
from lidarloc.core.sim.lidar_models import HDL64E_MAX_ELEVATION_DEG, HDL64E_MIN_ELEVATION_DEG, LidarModel
from lidarloc.core.sim.town import SENSOR_HEIGHT, SWAY_STD, TOWN_VERSION, TownSequence
from lidarloc.core.sim.town.drive import body_sway
from scipy.spatial import cKDTree


@pytest.fixture(scope="module")
def town(default_town) -> TownSequence:
    return default_town  # the default town and drive (made once per session)


@pytest.fixture(scope="module")
def small_town() -> TownSequence:
    return TownSequence(seed=3, extent_m=150.0, n_scans=40)


def _to_world(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]


# ------------------------------------------------------------------------------ scans
def test_scan_is_deterministic_per_seed_and_index(town, small_town):
    a, b = town.scan(7), town.scan(7)
    assert np.array_equal(a, b)
    c = town.scan(8)
    assert not (a.shape == c.shape and np.array_equal(a, c))
    # A second build from the same seed is the same town, drive and scans (the cache relies on it).
    again = TownSequence(seed=3, extent_m=150.0, n_scans=40)
    assert again.identity() == small_town.identity()
    np.testing.assert_array_equal(again.poses, small_town.poses)
    np.testing.assert_array_equal(again.scan(11), small_town.scan(11))
    # A pickled copy rebuilds its ray-casting scene from the same triangles.
    copy = pickle.loads(pickle.dumps(small_town))
    np.testing.assert_array_equal(copy.scan(11), small_town.scan(11))
    other = TownSequence(seed=4, extent_m=150.0, n_scans=40)
    assert other.identity() != small_town.identity()
    assert not np.allclose(other.poses[-1], small_town.poses[-1])


@pytest.mark.parametrize("i", [0, 333, 1100])
def test_scan_looks_like_an_hdl64e(town, i):
    pts = town.scan(i)
    assert pts.dtype == np.float32 and pts.ndim == 2 and pts.shape[1] == 4
    assert np.isfinite(pts).all()
    assert 60_000 < len(pts) <= 64 * LidarModel().n_azimuth
    r = np.linalg.norm(pts[:, :3], axis=1)
    assert r.max() <= 120.0
    assert r.min() > 1.0  # nothing inside the car itself (a parked car beside it can be ≈ 1.6 m away)
    elevation = np.degrees(np.arcsin(pts[:, 2] / r))
    margin = 0.05
    assert elevation.min() >= HDL64E_MIN_ELEVATION_DEG - margin
    assert elevation.max() <= HDL64E_MAX_ELEVATION_DEG + margin
    assert 0.0 <= pts[:, 3].min() and pts[:, 3].max() <= 1.0 and pts[:, 3].std() > 0.02
    # The road under the car is SENSOR_HEIGHT below the sensor: returns of the lowest beams.
    lowest = elevation < -22.0
    assert abs(np.median(pts[lowest, 2]) + SENSOR_HEIGHT) < 0.1


def test_consecutive_scans_agree_under_ground_truth_poses(town):
    """Scans i and i+1 mapped into the world with their poses overlap: poses and scans agree."""
    for i in (150, 640):
        a, b = town.scan(i), town.scan(i + 1)
        wa, wb = _to_world(town.poses[i], a), _to_world(town.poses[i + 1], b)

        def structure(pts, world):  # non-ground returns within 40 m
            r = np.linalg.norm(pts[:, :2], axis=1)
            return world[(pts[:, 2] > -SENSOR_HEIGHT + 0.4) & (r > 3.0) & (r < 40.0)]

        d, _ = cKDTree(structure(a, wa)).query(structure(b, wb))
        assert np.median(d) < 0.15, f"scans {i}, {i + 1}: median NN distance {np.median(d):.3f} m"


# ------------------------------------------------------------------------------ the drive
def test_default_drive(town):
    assert len(town) >= 1000
    np.testing.assert_allclose(np.diff(town.timestamps), 0.1, atol=1e-9)
    assert town.timestamps[0] == 0.0
    np.testing.assert_allclose(town.poses[0], np.eye(4), atol=1e-12)
    R = town.poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)


def test_drive_revisits_a_place(town):
    xy, t = town.poses[:, :2, 3], town.timestamps
    pairs = cKDTree(xy).query_pairs(5.0, output_type="ndarray")
    assert np.any(np.abs(t[pairs[:, 0]] - t[pairs[:, 1]]) >= 30.0)


def test_speed_profile_is_realistic(town):
    kmh = town.speeds * 3.6
    assert kmh.max() <= 50.0 + 1.0
    assert np.mean(kmh < 3.0) > 0.01  # it stops
    assert np.mean(kmh > 25.0) > 0.15  # and cruises
    dt = np.diff(town.timestamps)
    accel = np.diff(town.speeds)[:-1] / dt[:-1]
    assert np.abs(accel).max() < 4.0  # no jumps in speed
    yaw = np.unwrap(pose_to_xyz_ypr(town.poses)[:, 3])
    yaw_rate = np.abs(np.diff(yaw)) / dt
    turning = yaw_rate > np.radians(10.0)
    assert turning.any() and kmh[:-1][turning].max() < 25.0  # it slows down for turns


def test_car_follows_the_ground(town):
    """The sensor rides SENSOR_HEIGHT above the road and tilts with its slope."""
    world_to_town = inv_pose(town.town_to_world)
    p = town.poses_town[:, :3, 3]
    up = town.poses_town[:, :3, 2]
    under = p - SENSOR_HEIGHT * up
    np.testing.assert_allclose(under[:, 2], town.ground(under[:, 0], under[:, 1]), atol=0.02)
    assert np.ptp(p[:, 2]) > 0.2  # it is not flat
    assert np.degrees(np.arccos(up[:, 2])).max() < 6.0  # but gently sloped
    np.testing.assert_allclose(world_to_town @ town.poses, town.poses_town, atol=1e-9)


def test_body_sways_like_the_real_drives_car():
    """Pitch and roll on the suspension: σ SWAY_STD at speed, ~0.09° change per 0.1 s scan (as
    KITTI raw 0013's GPS/INS shows), still at a stop, the same for the same seed."""
    times = np.arange(20000) * 0.1
    speed = np.full(len(times), 10.0)
    speed[:1000] = 0.0
    pitch, roll = body_sway(np.random.default_rng(7), times, speed)
    for a in (pitch, roll):
        assert np.all(a[:1000] == 0.0)
        assert np.std(a[1000:]) == pytest.approx(SWAY_STD, rel=0.1)
        assert np.degrees(np.std(np.diff(a[1000:]))) == pytest.approx(0.09, abs=0.015)
    again = body_sway(np.random.default_rng(7), times, speed)
    np.testing.assert_array_equal(again[0], pitch)


def test_odometry_reads_the_first_steps_of_the_town_drive(town):
    """KISS-ICP measures the car's motion from the first scan (it read only about half of it
    when the simulated body followed the smooth ground exactly and the ground rings repeated)."""
    from kiss_icp.kiss_icp import KissICP
    from lidarloc.core.odometry.kiss import kiss_config

    icp = KissICP(kiss_config(100.0, 2.5, None))
    odom = []
    for k in range(11):
        icp.register_frame(town.scan(k)[:, :3].astype(np.float64), np.zeros(0))
        odom.append(icp.last_pose[:3, 3].copy())
    measured = np.linalg.norm(np.diff(odom, axis=0), axis=1)
    driven = np.linalg.norm(np.diff(town.poses[:11, :3, 3], axis=0), axis=1)
    assert measured.sum() == pytest.approx(driven.sum(), rel=0.03)
    assert np.all(np.abs(measured - driven) < 0.15)


def test_identity_and_config(town, small_town):
    ident = town.identity()
    for part in (f"v{TOWN_VERSION}", "seed=0", "size=400", "n_scans=1200"):
        assert part in ident
    assert town.name == "town-seed0"
    assert len(small_town) == 40 and "seed=3" in small_town.identity()
    assert small_town.scan(5).shape[1] == 4
    # the hook every Sequence implements for its error messages: a town scan never fails
    # validation, so no public call shows the description
    assert town.describe_scan(12) == "town seed 0 scan 12"
    lo, hi = town.extent
    assert np.all(hi - lo > [300.0, 300.0, 10.0])


def test_bad_arguments_are_reported():
    with pytest.raises(DataError, match="calib"):
        TownSequence(trajectory="poses.txt")
    with pytest.raises(DataError, match="extent_m"):
        TownSequence(extent_m=50.0)


# ------------------------------------------------------------------------------ along a KITTI drive
def test_town_along_kitti_trajectory(shared_data):
    root = shared_data / "kitti_odometry_poses"
    poses_file, calib_file = root / "poses" / "07.txt", root / "calib" / "07.txt"
    if not poses_file.is_file() or not calib_file.is_file():
        pytest.skip(f"KITTI odometry poses 07 not found under {root}")
    seq = TownSequence.from_config(TownConfig(), seed=1, trajectory=poses_file, calib=calib_file)
    cam0 = read_pose_lines(poses_file)
    lidar = cam0_to_lidar_poses(cam0, read_tr(calib_file))
    lidar = inv_pose(lidar[0])[None] @ lidar
    assert len(seq) == len(cam0)
    np.testing.assert_allclose(seq.poses, lidar, atol=1e-6)
    assert "07.txt" in seq.identity() and seq.name == "town-seed1-07"
    assert abs(np.median(np.diff(seq.timestamps)) - 0.1) < 0.01
    # Every pose is on the road, and the ground passes SENSOR_HEIGHT below the sensor.
    xy = seq.poses_town[:, :2, 3]
    assert seq.raster.lookup(seq.road, xy[:, 0], xy[:, 1]).all()
    assert seq.stats["ground_residual_median"] < 0.05
    # The town was grown around the drive: scans see buildings and trees, not just road.
    for i in (0, 550):
        pts = seq.scan(i)
        r = np.linalg.norm(pts[:, :3], axis=1)
        elevation = np.degrees(np.arcsin(pts[:, 2] / r))
        assert abs(np.median(pts[elevation < -22.0, 2]) + SENSOR_HEIGHT) < 0.15
        assert np.mean(pts[:, 2] > -SENSOR_HEIGHT + 0.4) > 0.15  # not only ground
