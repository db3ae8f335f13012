"""Motion skew and de-skew (core/odometry/deskew.py, the town's ``skew`` option): the sweep convention,
the constant-velocity de-skew, and that de-skewing the town's skewed scans with the true motion
gives back scans as exact as unskewed ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
from lidarloc.core.errors import LidarlocError
from lidarloc.core.geometry import inv_pose
from lidarloc.core.o3d import open3d
from lidarloc.core.odometry.deskew import deskew, sweep_offsets, twist_from_relative_pose
from lidarloc.core.sim.lidar_models import LidarModel
from lidarloc.core.sim.lidar_sim import Sweep, raycasting_scene
from lidarloc.core.sim.town import TownSequence
from lidarloc.core.sim.town.drive import interpolate_poses
from scipy.spatial.transform import Rotation


@pytest.fixture(scope="module")
def town(default_town) -> TownSequence:
    return default_town  # TownSequence.from_config(TownConfig(), seed=0), made once per session


@pytest.fixture(scope="module")
def surfaces(town):
    """Distance from town-frame points to the town's surfaces."""
    scene = raycasting_scene(town.lidar.parts, commit=True)
    return lambda pts: scene.compute_distance(open3d().core.Tensor(pts.astype(np.float32))).numpy()


def _on_surfaces(surfaces, T, scan):
    return surfaces(scan[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3])


def _true_motion(seq, i):
    """The sensor's velocity and angular velocity at scan i, from its neighbours' poses."""
    dt = seq.timestamps[i + 1] - seq.timestamps[i - 1]
    return twist_from_relative_pose(inv_pose(seq.poses[i - 1]) @ seq.poses[i + 1], dt)


# ------------------------------------------------------------------------------ the convention
def test_sweep_offsets_follow_the_convention():
    period = 0.1
    az = np.array([math.pi - 1e-6, math.pi / 2, 0.0, -math.pi / 2, -math.pi + 1e-6])
    pts = np.stack([10 * np.cos(az), 10 * np.sin(az), np.zeros(5)], axis=1)
    # starts just after straight behind, turns clockwise (left, ahead, right), ends behind
    np.testing.assert_allclose(sweep_offsets(pts, period), [-0.05, -0.025, 0.0, 0.025, 0.05], atol=1e-7)
    assert np.all(np.diff(sweep_offsets(pts, period)) > 0)
    with pytest.raises(LidarlocError, match="period"):
        sweep_offsets(pts, 0.0)
    with pytest.raises(LidarlocError, match="points"):
        sweep_offsets(np.zeros(3), period)


def test_deskew_moves_points_with_the_sensor():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-30, 30, (500, 3)), rng.random((500, 1))], axis=1).astype(np.float32)
    offsets = rng.uniform(-0.05, 0.05, 500)
    v, w = np.array([10.0, 0.5, 0.1]), np.array([0.01, -0.02, 0.4])
    out = deskew(pts, offsets, v, w)
    assert out.dtype == np.float32 and out.shape == pts.shape
    np.testing.assert_array_equal(out[:, 3], pts[:, 3])  # intensity kept
    want = Rotation.from_rotvec(offsets[:, None] * w).apply(pts[:, :3].astype(np.float64)) + offsets[:, None] * v
    np.testing.assert_allclose(out[:, :3], want, atol=1e-4)
    np.testing.assert_array_equal(deskew(pts, np.zeros(500), v, w), pts)  # mid-sweep points stay
    with pytest.raises(LidarlocError, match="offsets"):
        deskew(pts, offsets[:10], v, w)


def test_twist_from_relative_pose():
    v, w, dt = np.array([12.0, 0.3, -0.1]), np.array([0.02, 0.0, 0.5]), 0.1
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(w * dt).as_matrix()
    T[:3, 3] = T[:3, :3] @ v * dt  # the displacement, seen from the later frame, is v·dt
    got_v, got_w = twist_from_relative_pose(T, dt)
    np.testing.assert_allclose(got_v, v, atol=1e-12)
    np.testing.assert_allclose(got_w, w, atol=1e-12)
    with pytest.raises(LidarlocError, match="dt"):
        twist_from_relative_pose(T, 0.0)


# ------------------------------------------------------------------------------ the town's skew
def test_skewed_scan_deskewed_with_the_true_motion_is_exact(town, surfaces):
    """At ~11 m/s a skewed scan's points are off the surfaces by up to half a metre; de-skewed
    with the true motion they lie on them as closely as the unskewed scan's."""
    skewed = town.with_world(skew=True)
    speeds = town.speeds
    i = int(np.argmin(np.abs(speeds[50:600] - 11.0))) + 50
    assert speeds[i] > 9.0
    T = town.poses_town[i]
    plain, raw = town.scan(i), skewed.scan(i)
    fixed = deskew(raw, sweep_offsets(raw, 1.0 / town.rate_hz), *_true_motion(town, i))
    d_plain, d_raw, d_fixed = (_on_surfaces(surfaces, T, s) for s in (plain, raw, fixed))
    far = 0.1
    assert np.mean(d_raw > far) > 0.03  # skew is visible …
    assert np.mean(d_fixed > far) <= np.mean(d_plain > far) + 0.002  # … and de-skew removes it
    assert np.percentile(d_fixed, 90) < 1.1 * np.percentile(d_plain, 90)
    assert np.percentile(d_raw, 90) > 1.5 * np.percentile(d_plain, 90)
    # skew moves each point by where the sensor was: the de-skewed points are the raw ones moved
    # by at most speed × period / 2
    shift = np.linalg.norm(fixed[:, :3] - raw[:, :3], axis=1)
    assert shift.max() <= speeds[i] * 0.05 * 1.2 + 0.05


def test_noise_free_deskew_to_the_millimetre(town, surfaces):
    """Without range noise the de-skewed points are on the surfaces to a few millimetres (what
    remains is the constant-velocity model against the drive's interpolated motion)."""
    exact = town.lidar.with_model(LidarModel(range_sigma=0.0, dropout=0.0, weak_dropout=0.0, intensity_noise=0.0))
    i = 526
    P, times = town.poses_town, town.timestamps
    sweep = Sweep(0.1, lambda offsets: interpolate_poses(times, P, times[i] + offsets))
    raw = exact.scan(P[i], np.random.default_rng(1), sweep=sweep)
    fixed = deskew(raw, sweep_offsets(raw, 0.1), *_true_motion(town, i))
    d_raw, d_fixed = _on_surfaces(surfaces, P[i], raw), _on_surfaces(surfaces, P[i], fixed)
    assert np.median(d_fixed) < 0.002 and np.percentile(d_fixed, 90) < 0.01
    assert np.percentile(d_raw, 90) > 0.02
    # the wrong sign of the motion doubles the skew instead
    v, w = _true_motion(town, i)
    d_wrong = _on_surfaces(surfaces, P[i], deskew(raw, sweep_offsets(raw, 0.1), -v, -w))
    assert np.percentile(d_wrong, 90) > np.percentile(d_raw, 90)


def test_no_skew_at_a_standstill(town):
    """Where the car stands still the sweep's poses are all the same: skew changes nothing."""
    skewed = town.with_world(skew=True)
    still = np.flatnonzero(town.speeds[1:-1] < 1e-6) + 1
    still = still[(town.speeds[still - 1] < 1e-6)]
    assert len(still)
    i = int(still[0])
    a, b = skewed.scan(i), town.scan(i)
    assert a.shape == b.shape
    # (the body's sway differs by ~1e-7 rad between the poses around a stop: < 1 mm at 120 m)
    assert np.abs(a[:, :3] - b[:, :3]).max() < 1e-3
    assert skewed.map_source is town


def test_interpolated_poses_pass_through_the_drive(town):
    P, times = town.poses_town, town.timestamps
    got = interpolate_poses(times, P, times[100:110])
    np.testing.assert_allclose(got, P[100:110], atol=1e-9)
    mid = interpolate_poses(times, P, 0.5 * (times[100:110] + times[101:111]))
    np.testing.assert_allclose(mid[:, :3, 3], 0.5 * (P[100:110, :3, 3] + P[101:111, :3, 3]), atol=1e-9)
    R = mid[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
